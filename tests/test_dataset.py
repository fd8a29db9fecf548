"""A recorded expert dataset works with LeRobot's own tools: load, decode, train, visualize, push.

One tiny dataset (3 episodes, 32 px, with a checkpoint so it spans two files) is recorded once per
session through the same code as ``lerobot-suture record``. The Hub is offline (conftest); push tests
stop at the HTTP calls, which are replaced.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch

from lerobot_suture.datasets import metadata
from lerobot_suture.datasets.features import (
    ACTION_KEY,
    ENV_STATE_KEY,
    FPS,
    IMAGE_KEY,
    NEEDLE_KEYPOINTS_KEY,
    STATE_KEY,
    TASK,
    dataset_features,
)
from lerobot_suture.datasets.record import record, regenerate_episode
from lerobot_suture.datasets.record_config import RecordConfig
from lerobot_suture.datasets.split import (
    episode_seeds,
    split_episodes,
    train_episodes,
    validation_episodes,
    validation_seeds,
)
from lerobot_suture.datasets.video import resolve_video_backend

REPO_ID = "suture-tests/tiny_expert"
IMAGE_SIZE = 32
NUM_EPISODES = 3


@pytest.fixture(scope="session")
def tiny(tmp_path_factory):
    """The tiny dataset's RecordSummary (``.root`` is the dataset root)."""
    root = tmp_path_factory.mktemp("datasets") / "tiny_expert"
    cfg = RecordConfig(
        repo_id=REPO_ID,
        root=str(root),
        num_episodes=NUM_EPISODES,
        val_fraction=0.25,
        obs_type="pixels_agent_pos_state",
        image_size=IMAGE_SIZE,
        checkpoint_every=2,
    )
    return record(cfg)


@pytest.fixture(scope="session")
def backend() -> str:
    return resolve_video_backend()


def _load(root, backend, **kwargs):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset(REPO_ID, root=root, video_backend=backend, **kwargs)


def _tree_digest(root: Path) -> dict[str, str]:
    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


# ------------------------------------------------------------------------------------------ loading
def test_loads_offline_with_the_right_features_and_counts(tiny, backend):
    assert os.environ["HF_HUB_OFFLINE"] == "1"
    ds = _load(tiny.root, backend)
    log = metadata.read_episode_log(tiny.root)
    assert ds.num_episodes == NUM_EPISODES == len(log["episodes"])
    assert ds.num_frames == sum(e["length"] for e in log["episodes"]) == tiny.num_frames
    assert ds.fps == 10
    assert ds.meta.info.codebase_version == "v3.0"
    assert ds.meta.robot_type == "psm"
    features = ds.features
    assert features[IMAGE_KEY]["dtype"] == "video"
    assert tuple(features[IMAGE_KEY]["shape"]) == (IMAGE_SIZE, IMAGE_SIZE, 3)
    assert tuple(features[STATE_KEY]["shape"]) == (10,)
    assert tuple(features[ACTION_KEY]["shape"]) == (10,)
    assert tuple(features[ENV_STATE_KEY]["shape"]) == (18,)
    assert tuple(features[NEEDLE_KEYPOINTS_KEY]["shape"]) == (6,)
    item = ds[0]
    assert item[IMAGE_KEY].shape == (3, IMAGE_SIZE, IMAGE_SIZE)
    assert item[IMAGE_KEY].dtype == torch.float32
    assert item["task"] == TASK
    # The dataset spans two data files (a checkpoint after 2 episodes) and reads as one.
    assert len(list((tiny.root / "data").rglob("*.parquet"))) == 2
    assert sorted({int(i) for i in ds.hf_dataset["episode_index"]}) == list(range(NUM_EPISODES))


def test_frames_are_the_expert_episode_regenerated_from_its_seed(tiny, backend):
    episode = 2
    ds = _load(tiny.root, backend, episodes=[episode])
    regenerated = regenerate_episode(tiny.root, episode)
    n = len(ds)
    assert n == len(regenerated[ACTION_KEY])
    actions = torch.stack([ds[i][ACTION_KEY] for i in range(n)]).numpy()
    states = torch.stack([ds[i][STATE_KEY] for i in range(n)]).numpy()
    np.testing.assert_array_equal(actions, regenerated[ACTION_KEY])
    np.testing.assert_array_equal(states, regenerated[STATE_KEY])
    keypoints = torch.stack([ds[i][NEEDLE_KEYPOINTS_KEY] for i in range(n)]).numpy()
    np.testing.assert_array_equal(keypoints, regenerated[NEEDLE_KEYPOINTS_KEY])
    assert np.all(np.abs(keypoints) < 1)  # the needle stays in view
    # Video is lossy: decoded frames are close to the rendered ones, not equal.
    decoded = ds[n - 1][IMAGE_KEY].permute(1, 2, 0).numpy() * 255.0
    rendered = regenerated[IMAGE_KEY][n - 1].astype(np.float64)
    assert np.abs(decoded - rendered).mean() < 12.0
    assert bool(ds[n - 1]["next.success"]) and bool(ds[n - 1]["next.done"])
    assert not bool(ds[0]["next.done"])


def test_video_backend_is_the_one_lerobot_would_pick_and_decodes(tiny):
    from lerobot.utils.import_utils import get_safe_default_video_backend

    chosen = resolve_video_backend()
    # LeRobot's own choice (torchcodec when it loads, else pyav), made without its noisy fallback log.
    assert chosen == get_safe_default_video_backend()
    assert resolve_video_backend("pyav") == "pyav"
    with pytest.raises(ValueError, match="video_backend"):
        resolve_video_backend("ffmpeg")
    # Every frame of an episode decodes with it.
    ds = _load(tiny.root, chosen, episodes=[0])
    frames = torch.stack([ds[i][IMAGE_KEY] for i in range(len(ds))])
    assert frames.shape[1:] == (3, IMAGE_SIZE, IMAGE_SIZE)
    assert 0.0 <= float(frames.min()) and float(frames.max()) <= 1.0 and float(frames.std()) > 0.01


def test_video_backend_falls_back_past_a_decoder_that_fails_to_load_and_says_when_none_loads(
    tmp_path, monkeypatch
):
    """Real modules on the path: one fails at import as torchcodec does without FFmpeg, one loads."""
    from lerobot_suture.datasets.video import first_loading_backend

    (tmp_path / "suture_test_codec_without_ffmpeg.py").write_text(
        "raise OSError('libavutil.so.60: cannot open shared object file')\n"
    )
    (tmp_path / "suture_test_codec_that_loads.py").write_text("")
    monkeypatch.syspath_prepend(str(tmp_path))
    broken, loads = "suture_test_codec_without_ffmpeg", "suture_test_codec_that_loads"
    assert first_loading_backend({"first": broken, "second": loads}) == "second"
    assert first_loading_backend({"first": loads, "second": broken}) == "first"
    with pytest.raises(
        RuntimeError, match=r"No video decoder loads here .*apt-get install ffmpeg.*--video=false"
    ):
        first_loading_backend({"first": broken, "second": "suture_test_codec_not_installed"})


# --------------------------------------------------------------------------------- seeds and split
def test_episode_log_records_seeds_split_and_survives_finalize(tiny):
    log = metadata.read_episode_log(tiny.root)
    assert episode_seeds(tiny.root) == [0, 1, 2]  # the expert succeeds on the first seeds
    assert log["next_seed"] == 3 and log["discarded"] == []
    assert log["env_kwargs"] == {
        "obs_type": "pixels_agent_pos_state",
        "image_size": IMAGE_SIZE,
        "scenario": "nominal",
        "grasp": "narrow",
    }
    assert train_episodes(tiny.root) == [0, 1] and validation_episodes(tiny.root) == [2]
    assert validation_seeds(tiny.root) == [2]
    assert (tiny.train_episodes, tiny.val_episodes) == ([0, 1], [2])
    assert not (tiny.root / metadata.CHECKPOINT_PATH).exists()  # the recording finished cleanly
    info = json.loads((tiny.root / "meta" / "info.json").read_text())
    assert info["splits"] == {"train": "0:2", "val": "2:3"}
    assert log["command"].startswith("lerobot-suture record --repo_id=suture-tests/tiny_expert")


def test_lerobot_eval_split_holds_out_exactly_the_validation_episodes(tiny, backend):
    """LeRobot's own split of `--dataset.eval_split=<val_fraction>`, from a real TrainPipelineConfig: it trains
    on our train split and evaluates on val."""
    from lerobot.configs.default import DatasetConfig
    from lerobot.configs.train import TrainPipelineConfig
    from lerobot.datasets.factory import make_train_eval_datasets
    from policy_builders import tiny_config

    dataset_cfg = DatasetConfig(repo_id=REPO_ID, root=str(tiny.root), eval_split=0.25, video_backend=backend)
    cfg = TrainPipelineConfig(dataset=dataset_cfg, policy=tiny_config())
    train_ds, eval_ds = make_train_eval_datasets(cfg)
    assert train_ds.episodes == train_episodes(tiny.root)
    assert eval_ds.episodes == validation_episodes(tiny.root)
    # Frames come with the policy's history and horizon (its delta timestamps), from the right episodes.
    item = eval_ds[0]
    assert item[ACTION_KEY].shape == (cfg.policy.horizon, 10) and int(item["episode_index"]) == 2


def test_lerobot_train_trains_the_ensemble_on_the_recording_with_its_eval_split(tiny, backend, tmp_path):
    """The route the dataset card advertises, `--dataset.eval_split=0.25`, through the real `lerobot-train`
    with the ensemble: video, environment state and the needle keypoints as its auxiliary target."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot_policy_ensemble_diffusion import EnsembleDiffusionPolicy
    from policy_builders import tiny_policy_cli_args

    out = tmp_path / "train"
    cmd = [
        str(Path(sys.executable).parent / "lerobot-train"),
        f"--dataset.repo_id={REPO_ID}",
        f"--dataset.root={tiny.root}",
        "--dataset.eval_split=0.25",
        f"--dataset.video_backend={backend}",
        *tiny_policy_cli_args(),
        "--policy.vision_backbone_stages=1",
        "--policy.needle_keypoints_weight=1.0",
        "--batch_size=2",
        "--steps=2",
        "--eval_steps=2",
        "--log_freq=1",
        "--num_workers=0",
        f"--output_dir={out}",
    ]
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled"}
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-4000:]
    assert "Train/eval split: 2 train, 1 eval (eval_split=0.25" in log, log[-4000:]
    assert "step 2: eval_loss=" in log and "loss_needle_keypoints" in log, log[-4000:]

    model_dir = out / "checkpoints" / "last" / "pretrained_model"
    policy = EnsembleDiffusionPolicy.from_pretrained(model_dir)
    assert set(policy.config.input_features) == {IMAGE_KEY, STATE_KEY, ENV_STATE_KEY}
    assert policy.config.needle_keypoints_dim == 6
    # The trained ensemble acts on a recorded frame through its saved processors, in dataset units.
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=str(model_dir))
    frame = LeRobotDataset(REPO_ID, root=tiny.root, video_backend=backend)[0]
    observation = {k: v for k, v in frame.items() if k in policy.config.input_features}
    observation["task"] = frame["task"]
    action = postprocessor(policy.select_action(preprocessor(observation)))
    assert action.shape == (1, 10) and torch.isfinite(action).all()
    assert torch.isfinite(policy.last_prediction.score).all()


@pytest.mark.parametrize(
    "n, fraction, expected_val",
    [(133, 0.25, 34), (100, 0.25, 25), (3, 0.25, 1), (10, 0.0, 0), (2, 0.5, 1), (1, 0.0, 0), (0, 0.25, 0)],
)
def test_split_matches_lerobot_eval_split(n, fraction, expected_val):
    train, val = split_episodes(n, fraction)
    assert len(val) == expected_val == math.ceil(n * fraction)
    assert train + val == list(range(n))
    assert train or not n  # LeRobot's eval_split refuses a split without a training episode


@pytest.mark.parametrize("n, fraction", [(1, 0.5), (1, 0.25), (2, 0.75), (3, 0.9)])
def test_split_without_a_training_episode_is_refused_as_lerobot_refuses_it(n, fraction):
    with pytest.raises(
        ValueError, match=f"`val_fraction`={fraction} holds out all {n} episode.*none to train"
    ):
        split_episodes(n, fraction)


def test_split_rejects_bad_fraction():
    with pytest.raises(ValueError, match="val_fraction"):
        split_episodes(10, 1.0)


def test_the_policy_packages_suture_features_are_the_recorded_datasets():
    """The policy distribution does not import the env's, so its test and benchmark features are copies:
    a recording that changes a shape must fail here, not on a user's checkpoint."""
    import policy_builders as testing

    recorded = dataset_features("pixels_agent_pos", testing.IMAGE_SIZE, video=False)
    for key, spec in testing.SUTURE_DATASET_FEATURES.items():
        assert tuple(recorded[key]["shape"]) == tuple(spec["shape"]), key
    assert recorded[NEEDLE_KEYPOINTS_KEY]["shape"] == (testing.NEEDLE_KEYPOINTS_DIM,)
    assert testing.IMAGE_KEY == IMAGE_KEY and testing.FPS == FPS


# -------------------------------------------------------------------------------------------- card
def test_dataset_card_says_what_the_dataset_is(tiny):
    card = (tiny.root / "README.md").read_text()
    log = metadata.read_episode_log(tiny.root)
    for needle in (
        "license: apache-2.0",
        "- lerobot-suture",
        "- LeRobot",
        "Safe Uncertainty-Aware Learning of Robotic Suturing",
        "arXiv:2505.16596",
        TASK,
        "phantom yaw",
        "±10 mm",
        "ScriptedExpert",
        "| train | 2 | 0-1 |",
        "| val | 1 | 2 |",
        "--dataset.eval_split=0.25",
        "`observation.images.endoscope` | video | (32, 32, 3)",
        "`observation.environment_state` | float32 | (18,)",
        "`observation.needle_keypoints` | float32 | (6,)",
        log["command"],
        "License: Apache-2.0",
    ):
        assert needle in card, needle
    assert "{{" not in card and "{%" not in card


# ---------------------------------------------------------------------------------- lerobot tools
def test_lerobot_train_runs_on_the_train_split(tiny, backend, tmp_path):
    """The real `lerobot-train` command: a tiny diffusion policy, 2 steps on the train episodes, CPU."""
    episodes = ",".join(str(i) for i in train_episodes(tiny.root))
    cmd = [
        str(Path(sys.executable).parent / "lerobot-train"),
        f"--dataset.repo_id={REPO_ID}",
        f"--dataset.root={tiny.root}",
        f"--dataset.episodes=[{episodes}]",
        f"--dataset.video_backend={backend}",
        "--policy.type=diffusion",
        "--policy.device=cpu",
        "--policy.pretrained_backbone_weights=null",
        "--policy.use_group_norm=true",
        "--policy.push_to_hub=false",
        "--policy.down_dims=[32,64]",
        "--policy.horizon=8",
        "--policy.n_action_steps=4",
        "--policy.n_obs_steps=2",
        "--batch_size=2",
        "--steps=2",
        "--num_workers=0",
        "--save_checkpoint=false",
        f"--output_dir={tmp_path / 'train'}",
    ]
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled", "OMP_NUM_THREADS": "2"}
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-4000:]
    assert "dataset.num_episodes=2" in out and "End of training" in out, out[-4000:]


def _rrd_images(rrd: Path, entity: str) -> dict[int, np.ndarray]:
    """The raw RGB images logged to `entity` in an .rrd file, by `frame_index`, as rerun reads them back."""
    # rerun >= 0.32 reads files through `experimental.RrdReader` (its dataframe API was removed).
    from rerun.experimental import RrdReader

    images = {}
    for chunk in RrdReader(rrd).stream():
        if chunk.entity_path != entity:
            continue
        batch = chunk.to_record_batch().to_pydict()
        for index, (fmt,), (buffer,) in zip(
            batch["frame_index"], batch["Image:format"], batch["Image:buffer"], strict=True
        ):
            images[index] = np.asarray(buffer, dtype=np.uint8).reshape(fmt["height"], fmt["width"], -1)
    return images


@pytest.mark.slow
def test_lerobot_dataset_viz_saves_an_episode_rerun_reads_back(tiny, backend, tmp_path):
    """The real `lerobot-dataset-viz --save 1` writes an .rrd that rerun loads: every frame of the episode."""
    from rerun.experimental import RrdReader

    episode = 1
    cmd = [
        str(Path(sys.executable).parent / "lerobot-dataset-viz"),
        "--repo-id",
        REPO_ID,
        "--root",
        str(tiny.root),
        "--episode-index",
        str(episode),
        "--save",
        "1",
        "--output-dir",
        str(tmp_path),
        "--num-workers",
        "0",
    ]
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "2"}
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-4000:]
    rrd = tmp_path / f"{REPO_ID.replace('/', '_')}_episode_{episode}.rrd"
    # The episode's raw 32x32 RGB frames alone are 3 kB each.
    assert rrd.is_file() and rrd.stat().st_size > 10 * IMAGE_SIZE * IMAGE_SIZE * 3

    entities = set(RrdReader(rrd).store().schema().entity_paths())
    assert {f"/{IMAGE_KEY}", "/action", "/state", "/next.success"} <= entities, entities
    images = _rrd_images(rrd, f"/{IMAGE_KEY}")
    length = metadata.read_episode_log(tiny.root)["episodes"][episode]["length"]
    assert sorted(images) == list(range(length))
    # The logged frames are the dataset's decoded frames, not blank ones.
    ds = _load(tiny.root, backend, episodes=[episode])
    for i in (0, length - 1):
        decoded = (ds[i][IMAGE_KEY].permute(1, 2, 0).numpy() * 255).astype(np.uint8)
        assert images[i].shape == (IMAGE_SIZE, IMAGE_SIZE, 3) and images[i].std() > 1.0
        assert np.abs(images[i].astype(np.int16) - decoded).max() <= 1


# --------------------------------------------------------------------------------------------- hub
@pytest.fixture
def online_without_token(monkeypatch, tmp_path):
    """The Hub switched on (conftest switches it off) and no token anywhere."""
    from huggingface_hub import constants

    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", False)
    monkeypatch.setattr(constants, "HF_TOKEN_PATH", str(tmp_path / "no_token"))
    monkeypatch.delenv("HF_TOKEN", raising=False)
    monkeypatch.delenv("HUGGING_FACE_HUB_TOKEN", raising=False)


def test_push_without_token_fails_fast_and_keeps_the_dataset(tiny, online_without_token):
    from lerobot_suture.datasets.hub import HubPushError, push_dataset

    before = _tree_digest(tiny.root)
    with pytest.raises(HubPushError, match="No Hugging Face token: log in with `hf auth login`"):
        push_dataset(REPO_ID, tiny.root)
    assert _tree_digest(tiny.root) == before


def test_push_in_offline_mode_says_so(tiny):
    from lerobot_suture.datasets.hub import HubPushError, push_dataset

    with pytest.raises(HubPushError, match="HF_HUB_OFFLINE is set"):
        push_dataset(REPO_ID, tiny.root)


def test_push_command_reports_errors(tiny, capsys):
    from lerobot_suture.cli import main as cli_main

    with pytest.raises(SystemExit) as exit_:
        cli_main(["push", "--repo_id=not-a-repo-id"])
    assert exit_.value.code == 2 and "USER/NAME" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:
        cli_main(["push", f"--repo_id={REPO_ID}", f"--root={tiny.root}"])
    assert exit_.value.code == 1 and "HF_HUB_OFFLINE is set" in capsys.readouterr().err


def test_push_without_network_fails_fast_and_keeps_the_dataset(tiny, online_without_token, monkeypatch):
    import httpx
    from huggingface_hub import HfApi

    from lerobot_suture.datasets.hub import HubPushError, push_dataset

    monkeypatch.setenv("HF_TOKEN", "hf_test_token")

    def unreachable(self, *args, **kwargs):
        raise httpx.ConnectError("[Errno -3] Temporary failure in name resolution")

    monkeypatch.setattr(HfApi, "whoami", unreachable)
    before = _tree_digest(tiny.root)
    with pytest.raises(HubPushError, match="Cannot reach the Hugging Face Hub"):
        push_dataset(REPO_ID, tiny.root)
    assert _tree_digest(tiny.root) == before


def test_push_uses_lerobot_push_to_hub_with_tags_and_card(tiny, online_without_token, monkeypatch):
    """Everything up to the HTTP calls runs; those are recorded instead of sent."""
    import httpx
    from huggingface_hub import DatasetCard, HfApi

    from lerobot_suture.datasets.hub import HubPushError, push_dataset

    monkeypatch.setenv("HF_TOKEN", "hf_test_token")
    calls: dict[str, list] = {}

    def recorder(name, result=None):
        def call(self, *args, **kwargs):
            calls.setdefault(name, []).append(kwargs)
            return result

        return call

    monkeypatch.setattr(
        HfApi, "whoami", recorder("whoami", {"name": "someone", "orgs": [{"name": "suture-tests"}]})
    )
    for name in ("create_repo", "upload_folder", "create_tag", "delete_tag", "create_branch"):
        monkeypatch.setattr(HfApi, name, recorder(name))
    pushed_cards = []
    monkeypatch.setattr(DatasetCard, "push_to_hub", lambda self, **kw: pushed_cards.append((str(self), kw)))

    before = _tree_digest(tiny.root)
    url = push_dataset(REPO_ID, tiny.root, private=True)
    assert url == f"https://huggingface.co/datasets/{REPO_ID}"
    assert calls["create_repo"][0]["repo_id"] == REPO_ID and calls["create_repo"][0]["private"] is True
    upload = calls["upload_folder"][0]
    assert Path(upload["folder_path"]) == tiny.root and upload["repo_type"] == "dataset"
    assert calls["create_tag"][0]["tag"] == "v3.0"
    card, kwargs = pushed_cards[0]
    assert kwargs["repo_id"] == REPO_ID
    assert "- lerobot-suture" in card and "Safe Uncertainty-Aware Learning of Robotic Suturing" in card
    assert card.strip() == (tiny.root / "README.md").read_text().strip()  # the local card is the Hub's
    assert _tree_digest(tiny.root) == before

    # An upload that breaks off leaves the local dataset as it was and says how to retry.
    def broken_upload(self, *args, **kwargs):
        raise httpx.ReadTimeout("The read operation timed out")

    monkeypatch.setattr(HfApi, "upload_folder", broken_upload)
    with pytest.raises(HubPushError, match="intact; push it later with `lerobot-suture push"):
        push_dataset(REPO_ID, tiny.root)
    assert _tree_digest(tiny.root) == before

    # A namespace the token cannot write to is refused before anything is uploaded.
    calls.clear()
    with pytest.raises(HubPushError, match="cannot write to 'elsewhere'"):
        push_dataset("elsewhere/tiny_expert", tiny.root)
    assert "upload_folder" not in calls


def _load_benchmark(name: str) -> types.ModuleType:
    """A script of `studies/benchmarks/` imported as a module."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        name, Path(__file__).resolve().parents[1] / "studies" / "benchmarks" / f"{name}.py"
    )
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    return bench


def _tiny_visual_config(image_size: int):
    """A tiny 2-member ensemble reading the endoscope image (no resize or crop) and the state."""
    from lerobot.configs.types import FeatureType, PolicyFeature
    from policy_builders import tiny_config

    return tiny_config(
        n_members=2,
        num_inference_steps=2,
        noise_scheduler_type="DDIM",
        resize_shape=None,
        crop_ratio=1.0,
        input_features={
            "observation.images.endoscope": PolicyFeature(FeatureType.VISUAL, (3, image_size, image_size)),
            "observation.state": PolicyFeature(FeatureType.STATE, (10,)),
        },
    )


def test_open_loop_error_benchmark_scores_a_checkpoint_on_the_validation_frames(tiny, tmp_path):
    """`studies/benchmarks/open_loop_error.py` on a tiny untrained ensemble saved as lerobot-train saves one."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from policy_builders import save_untrained_policy

    bench = _load_benchmark("open_loop_error")

    stats = LeRobotDataset(REPO_ID, root=tiny.root).meta.stats
    torch.manual_seed(0)
    config = _tiny_visual_config(image_size=IMAGE_SIZE)
    run = tmp_path / "checkpoints"
    directory = save_untrained_policy(config, stats, run / "000002" / "pretrained_model")

    assert bench.checkpoint_dirs([str(run)]) == [directory]
    with pytest.raises(FileNotFoundError, match="pretrained_model"):
        bench.checkpoint_dirs([str(tmp_path / "nothing")])
    first = bench.open_loop_error(directory, Path(tiny.root), n_frames=16, seed=0, device="cpu")
    again = bench.open_loop_error(directory, Path(tiny.root), n_frames=16, seed=0, device="cpu")
    assert first["frames"] > 0 and first["members"] == 2
    assert all(
        math.isfinite(first[k]) and first[k] >= 0 for k in ("first_action_mm", "last_action_mm", "stay_mm")
    )
    # Seeded: the same frames and the same diffusion noise give the same numbers.
    assert {k: v for k, v in first.items() if k != "seconds"} == {
        k: v for k, v in again.items() if k != "seconds"
    }
    # Chosen episodes instead of the validation split (a DAgger round's surgeon segments).
    assert bench.parse_episodes("all", Path(tiny.root)) == list(range(tiny.num_episodes))
    assert bench.parse_episodes("0,2", Path(tiny.root)) == [0, 2]
    with pytest.raises(SystemExit, match="comma-separated"):
        bench.parse_episodes("first", Path(tiny.root))
    one = bench.open_loop_error(directory, Path(tiny.root), n_frames=8, seed=0, device="cpu", episodes=[0])
    assert 0 < one["frames"] <= 8
    binned = bench.open_loop_error(
        directory, Path(tiny.root), n_frames=16, seed=0, device="cpu", episodes=[0], frame_bins=[0, 3]
    )
    by_frame = binned["first_action_mm_by_frame"]
    assert list(by_frame) == ["0-2", "3-"]
    assert sum(b["frames"] for b in by_frame.values()) == 16
    assert bench.parse_frame_bins("0,3,8") == [0, 3, 8]
    with pytest.raises(SystemExit, match="increase"):
        bench.parse_frame_bins("3,3")


def test_needle_attention_benchmark_probes_a_checkpoint(tiny, tmp_path):
    """`studies/benchmarks/needle_attention.py` on a tiny untrained ensemble: needle hidden, noise, phantom moved."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from policy_builders import save_untrained_policy

    bench = _load_benchmark("needle_attention")

    torch.manual_seed(0)
    config = _tiny_visual_config(image_size=96)
    stats = LeRobotDataset(REPO_ID, root=tiny.root).meta.stats
    directory = save_untrained_policy(config, stats, tmp_path / "pretrained_model")
    # Probe seed 3,000,000: the expert's needle enters the tissue at step 19, so step 25 is inserted.
    first = bench.needle_attention(directory, episodes=1, probe_steps=[3, 25], device="cpu")
    again = bench.needle_attention(directory, episodes=1, probe_steps=[3, 25], device="cpu")
    assert first["frames"] == 2 and first["needle_pixels"] > 0
    assert first["inserted"]["frames"] == 1
    for report in (first, first["inserted"]):
        for key in (
            "hidden_shift_mm",
            "noise_shift_mm",
            "phantom_shift_mm",
            "hidden_score_ratio",
            "phantom_score_ratio",
        ):
            assert math.isfinite(report[key]) and report[key] >= 0
    before_insertion = bench.needle_attention(directory, episodes=1, probe_steps=[3], device="cpu")
    assert before_insertion["inserted"] == {"frames": 0} | {
        key: None for key in before_insertion["inserted"] if key != "frames"
    }
    # Seeded: the same probe seeds and diffusion noise give the same numbers.
    assert {k: v for k, v in first.items() if k != "seconds"} == {
        k: v for k, v in again.items() if k != "seconds"
    }
