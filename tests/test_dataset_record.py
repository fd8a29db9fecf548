"""``lerobot-suture record`` as a user meets it: bad flags, existing roots, discards, interrupts, resume."""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from lerobot_suture.cli import main as cli_main
from lerobot_suture.datasets import metadata
from lerobot_suture.datasets.expert_episode import expert_episode_frames, make_env
from lerobot_suture.datasets.features import ACTION_KEY, DONE_KEY, SUCCESS_KEY
from lerobot_suture.datasets.record import record, regenerate_episode
from lerobot_suture.datasets.record_config import MAX_STEPS_AFTER_SUCCESS, RecordConfig, expert_config
from lerobot_suture.datasets.split import episode_seeds
from lerobot_suture.datasets.stop_signals import RecordingInterrupted
from lerobot_suture.datasets.video import resolve_video_backend
from lerobot_suture.expert import ScriptedExpert

REPO_ID = "suture-tests/record"
SMALL = {"image_size": 32, "obs_type": "pixels_agent_pos"}
ONE = {"num_episodes": 1, "val_fraction": 0.0}  # a single episode is for training: none held out


def _cfg(root: Path, **kwargs) -> RecordConfig:
    return RecordConfig(repo_id=REPO_ID, root=str(root), **{**SMALL, **kwargs})


def _load(root: Path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset(REPO_ID, root=root, video_backend=resolve_video_backend())


def _assert_consistent(root: Path, n_episodes: int) -> None:
    """LeRobot loads the dataset; counts agree with the episode log; no recording is pending."""
    ds = _load(root)
    log = metadata.read_episode_log(root)
    assert ds.num_episodes == n_episodes == len(log["episodes"])
    assert ds.num_frames == sum(e["length"] for e in log["episodes"])
    assert [e["episode_index"] for e in log["episodes"]] == list(range(n_episodes))
    assert not (root / metadata.CHECKPOINT_PATH).exists()
    assert not [p for p in (root / "images").rglob("*") if p.is_file()]  # no staged frames left
    ds[len(ds) - 1]  # the last frame decodes


# ------------------------------------------------------------------------------------ bad input
@pytest.mark.parametrize(
    "repo_id, match",
    [
        ("", "`repo_id` is required"),
        ("no_namespace", "USER/NAME with exactly one '/'"),
        ("a/b/c", "USER/NAME with exactly one '/'"),
        ("user/bad name", "not a valid Hugging Face repo id"),
        ("user/double--dash", "not a valid Hugging Face repo id"),
    ],
)
def test_malformed_repo_id_is_an_error_before_any_work(repo_id, match, tmp_path, capsys):
    root = tmp_path / "ds"
    with pytest.raises(ValueError, match=match):
        RecordConfig(repo_id=repo_id, root=str(root))
    with pytest.raises(SystemExit) as exit_:
        cli_main(["record", f"--repo_id={repo_id}", f"--root={root}"])
    assert exit_.value.code == 2
    assert match.split("`")[-1].strip() in capsys.readouterr().err
    assert not root.exists()


@pytest.mark.parametrize(
    "flag, match",
    [
        ("--num_episodes=0", "`num_episodes` must be >= 1"),
        ("--val_fraction=1.0", r"`val_fraction` must be in \[0, 1\)"),
        ("--num_episodes=1", r"`val_fraction`=0.25 holds out all 1 episode\(s\) and leaves none to train"),
        ("--num_episodes=3 --val_fraction=0.7", r"`val_fraction`=0.7 holds out all 3 episode\(s\)"),
        ("--obs_type=rgb", "`obs_type` must be one of"),
        ("--scenario=earthquake", "`scenario` must be one of"),
        ("--image_size=8", r"`image_size` must be in \[16, 640\]"),
        ("--checkpoint_every=0", "`checkpoint_every` must be >= 1"),
        ("--steps_after_success=11", r"`steps_after_success` must be in \[0, 10\] control steps"),
        ("--steps_after_success=-1", r"`steps_after_success` must be in \[0, 10\] control steps"),
        ("--grasp=loose", r"`grasp` must be one of \['narrow', 'wide'\]"),
    ],
)
def test_bad_flags_name_the_field(flag, match, tmp_path):
    import draccus

    with pytest.raises(draccus.utils.ParsingError) as err:
        draccus.parse(RecordConfig, args=[f"--repo_id={REPO_ID}", f"--root={tmp_path / 'ds'}", *flag.split()])
    assert isinstance(err.value.__cause__, ValueError)
    with pytest.raises(ValueError, match=match):
        raise err.value.__cause__


@pytest.mark.parametrize("recipe, episodes", [("suture_expert.yaml", 133), ("suture_demo.yaml", 12)])
def test_dataset_recipes_parse(recipe, episodes):
    from lerobot_suture.datasets.record_config import parse_config

    path = Path(__file__).parents[1] / "recipes" / recipe
    cfg = parse_config([f"--config_path={path}", f"--repo_id={REPO_ID}", "--seed=3"])
    assert (cfg.num_episodes, cfg.val_fraction, cfg.image_size, cfg.seed) == (episodes, 0.25, 96, 3)
    assert cfg.obs_type == "pixels_agent_pos" and cfg.video and not cfg.push_to_hub


def test_the_grasp_blind_expert_plans_with_the_nominal_grasp(tmp_path):
    from lerobot_suture.datasets.record_config import expert_config

    assert not expert_config(0).assume_nominal_grasp
    blind = expert_config(3, grasp_blind_expert=True)
    assert blind.assume_nominal_grasp and blind.protrusion_angle == expert_config(3).protrusion_angle
    cfg = _cfg(tmp_path / "ds", grasp_blind_expert=True, grasp="wide")
    assert "--grasp=wide --grasp_blind_expert=true" in cfg.command()


def test_regrasp_miss_and_noise_reach_the_expert_and_only_tasks_that_regrasp(tmp_path):
    assert expert_config(0, regrasp_miss=0.001).regrasp_miss == 0.001 and expert_config(0).regrasp_miss == 0.0
    cfg = _cfg(tmp_path / "ds", task="extraction", regrasp_miss=0.001)
    assert "--regrasp_miss=0.001" in cfg.command()
    with pytest.raises(ValueError, match="task 'insertion' has none. Use it with --task=extraction"):
        _cfg(tmp_path / "ds", regrasp_miss=0.001)
    with pytest.raises(ValueError, match="`regrasp_miss` must be 0"):
        _cfg(tmp_path / "ds", task="running_suture", regrasp_miss=0.0001)
    cfg = _cfg(tmp_path / "ds", task="running_suture", regrasp_noise=0.0004)
    assert "--regrasp_noise=0.0004" in cfg.command() and expert_config(0, regrasp_noise=0.0004).regrasp_noise
    with pytest.raises(ValueError, match="`regrasp_noise` shapes an extraction's regrasp; task 'pickup'"):
        _cfg(tmp_path / "ds", task="pickup", regrasp_noise=0.0004)
    with pytest.raises(ValueError, match=r"`regrasp_noise` must be in \[0, 0.002\] m"):
        _cfg(tmp_path / "ds", task="extraction", regrasp_noise=0.01)
    cfg = _cfg(tmp_path / "ds", task="extraction", regrasp_settle=3, regrasp_reach_offset=0.001)
    assert "--regrasp_settle=3 --regrasp_reach_offset=0.001" in cfg.command()
    expert = expert_config(0, regrasp_settle=3, regrasp_reach_offset=0.001)
    assert (expert.regrasp_settle, expert.regrasp_reach_offset) == (3, 0.001)
    with pytest.raises(ValueError, match="`regrasp_settle` shapes an extraction's regrasp; task 'insertion'"):
        _cfg(tmp_path / "ds", regrasp_settle=3)
    with pytest.raises(ValueError, match=r"`regrasp_reach_offset` must be in \[0, 0.003\] m"):
        _cfg(tmp_path / "ds", task="extraction", regrasp_reach_offset=0.01)


@pytest.mark.parametrize("detour", [-0.001, 0.05, float("nan")])
def test_approach_detour_out_of_range_names_the_expert_s_range(tmp_path, detour):
    with pytest.raises(ValueError, match=r"`approach_detour` must be in \[0, 0.03\] m"):
        _cfg(tmp_path / "ds", approach_detour=detour)


def test_existing_root_without_resume_is_an_error(tmp_path, capsys):
    root = tmp_path / "ds"
    root.mkdir()
    (root / "something.txt").write_text("not mine")
    with pytest.raises(FileExistsError, match="already exists. Pass --resume=true"):
        record(_cfg(root, **ONE))
    with pytest.raises(SystemExit) as exit_:
        cli_main(["record", f"--repo_id={REPO_ID}", f"--root={root}", "--num_episodes=1", "--val_fraction=0"])
    assert exit_.value.code == 2 and "--resume=true" in capsys.readouterr().err
    assert sorted(p.name for p in root.iterdir()) == ["something.txt"]


def test_resume_without_a_dataset_is_an_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="no dataset at .* to resume"):
        record(_cfg(tmp_path / "missing", **ONE, resume=True))
    foreign = tmp_path / "foreign"
    (foreign / "meta").mkdir(parents=True)
    (foreign / "meta" / "info.json").write_text("{}")
    with pytest.raises(FileNotFoundError, match="not recorded by `lerobot-suture record`"):
        record(_cfg(foreign, **ONE, resume=True))


def test_push_without_token_fails_before_recording(tmp_path, monkeypatch):
    from huggingface_hub import constants

    from lerobot_suture.datasets.hub import HubPushError

    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", False)
    monkeypatch.setattr(constants, "HF_TOKEN_PATH", str(tmp_path / "no_token"))
    monkeypatch.delenv("HF_TOKEN", raising=False)
    monkeypatch.delenv("HUGGING_FACE_HUB_TOKEN", raising=False)
    root = tmp_path / "ds"
    with pytest.raises(HubPushError, match="No Hugging Face token"):
        record(_cfg(root, **ONE, push_to_hub=True))
    assert not root.exists()


@pytest.mark.parametrize(
    "obs_type, video, image_dtype",
    [("pixels_agent_pos", False, "image"), ("state", True, None)],
)
def test_other_storage_layouts_load(tmp_path, obs_type, video, image_dtype):
    """PNG frames instead of video, and the image-free state layout, are datasets LeRobot loads."""
    root = tmp_path / "ds"
    record(_cfg(root, **ONE, obs_type=obs_type, video=video))
    _assert_consistent(root, 1)
    features = _load(root).features
    assert features.get("observation.images.endoscope", {}).get("dtype") == image_dtype
    assert ("observation.environment_state" in features) == (obs_type == "state")
    assert ("observation.needle_keypoints" in features) == (obs_type != "state")


def test_steps_after_success_record_the_expert_driving_on(tmp_path):
    """The episode goes on past success with the expert still turning the needle; it regenerates, and a
    resume must keep the setting."""
    extra = MAX_STEPS_AFTER_SUCCESS
    root = tmp_path / "ds"
    record(_cfg(root, **ONE, obs_type="state", steps_after_success=extra))
    _assert_consistent(root, 1)
    frames = regenerate_episode(root, 0)
    env = make_env("state", 32, "nominal")
    try:
        at_success = expert_episode_frames(env, ScriptedExpert(), seed=0)
    finally:
        env.close()
    n = at_success.length
    assert len(frames[ACTION_KEY]) == n + extra
    # Up to success the same insertion; the raised protrusion only moves where the drive stops.
    np.testing.assert_array_equal(
        frames[ACTION_KEY][:n], np.stack([f[ACTION_KEY] for f in at_success.frames])
    )
    assert frames[SUCCESS_KEY][n - 1 :].all() and not frames[SUCCESS_KEY][: n - 1].any()
    assert frames[DONE_KEY][-1] and not frames[DONE_KEY][:-1].any()
    # Still driving at the last frame: the jaw target moves as much per step as before success.
    step_mm = np.linalg.norm(np.diff(frames[ACTION_KEY][:, :3], axis=0), axis=1) * 1e3
    assert step_mm[-1] == pytest.approx(step_mm[n - 2], rel=0.05) and step_mm[-1] > 0.3
    assert metadata.read_episode_log(root)["expert"]["config"]["protrusion_angle"] > 0.5
    with pytest.raises(ValueError, match="recorded with --steps_after_success=10"):
        record(_cfg(root, num_episodes=2, obs_type="state", resume=True))


def test_episodes_past_success_are_discarded_when_cut_short_or_lost(monkeypatch):
    import gymnasium as gym

    from lerobot_suture import ENV_ID
    from lerobot_suture.sim.suture_env import SutureEnv

    env = make_env("state", 32, "nominal")
    n = expert_episode_frames(env, ScriptedExpert(), seed=0).length
    env.close()
    # The time limit falls 2 steps after success: 5 were asked for.
    env = gym.make(ENV_ID, obs_type="state", max_episode_steps=n + 2, disable_env_checker=True)
    cut = expert_episode_frames(env, ScriptedExpert(expert_config(5)), seed=0, steps_after_success=5)
    assert not cut.success and cut.reason == "time limit after success" and cut.length == n + 2
    # The insertion stops counting as on the marks 3 steps after success.
    outcome = SutureEnv._task_outcome
    calls = {"after": 0}

    def lapsing(self):
        over, on_the_marks = outcome(self)
        if over:
            calls["after"] += 1
        return over, on_the_marks and calls["after"] < 4

    monkeypatch.setattr(SutureEnv, "_task_outcome", lapsing)
    env = make_env("state", 32, "nominal")
    lost = expert_episode_frames(env, ScriptedExpert(expert_config(5)), seed=0, steps_after_success=5)
    env.close()
    assert not lost.success and lost.reason == "success lost while driving on"
    assert f"lost it at step {n + 3}" in lost.detail and "--steps_after_success" in lost.detail


# ------------------------------------------------------------------------------ discards, interrupts
def test_failed_attempts_are_discarded_with_their_reason(tmp_path, monkeypatch):
    """The jaw loses the needle in the first attempt: that episode is discarded and logged."""
    act = ScriptedExpert.act
    state = {"calls": 0}

    def dropping_act(self, env):
        state["calls"] += 1
        if state["calls"] == 5:  # first attempt only
            env.unwrapped.release_needle()
        return act(self, env)

    monkeypatch.setattr(ScriptedExpert, "act", dropping_act)
    root = tmp_path / "ds"
    summary = record(_cfg(root, **ONE))
    assert summary.discarded == 1 and summary.discard_reasons == {"needle dropped": 1}
    log = metadata.read_episode_log(root)
    assert log["discarded"][0]["seed"] == 0 and log["discarded"][0]["reason"] == "needle dropped"
    assert log["discarded"][0]["steps"] == 100  # the expert held still until the time limit
    assert episode_seeds(root) == [1]
    assert "1 expert attempts were discarded (1 needle dropped)" in (root / "README.md").read_text()
    _assert_consistent(root, 1)


def test_interrupts_keep_finished_episodes_and_resume_continues(tmp_path, monkeypatch):
    """Ctrl-C while an episode is saved, then kill (SIGTERM) mid-rollout, then resume to the end."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = tmp_path / "ds"
    save_episode = LeRobotDataset.save_episode
    saves = {"n": 0}

    def save_and_ctrl_c(self, *args, **kwargs):
        saves["n"] += 1
        if saves["n"] == 2:  # arrives mid-save: held back until the episode is on disk
            os.kill(os.getpid(), signal.SIGINT)
        return save_episode(self, *args, **kwargs)

    monkeypatch.setattr(LeRobotDataset, "save_episode", save_and_ctrl_c)
    with pytest.raises(RecordingInterrupted) as stop:
        record(_cfg(root, num_episodes=3))
    assert stop.value.signum == signal.SIGINT
    _assert_consistent(root, 2)
    monkeypatch.setattr(LeRobotDataset, "save_episode", save_episode)

    act = ScriptedExpert.act
    calls = {"n": 0}

    def act_then_kill(self, env):
        calls["n"] += 1
        if calls["n"] == 20:
            os.kill(os.getpid(), signal.SIGTERM)
        return act(self, env)

    monkeypatch.setattr(ScriptedExpert, "act", act_then_kill)
    with pytest.raises(RecordingInterrupted) as stop:
        record(_cfg(root, num_episodes=3, resume=True))
    assert stop.value.signum == signal.SIGTERM
    _assert_consistent(root, 2)  # the episode in flight is dropped, nothing else
    monkeypatch.setattr(ScriptedExpert, "act", act)

    summary = record(_cfg(root, num_episodes=3, resume=True))
    assert summary.added_episodes == 1
    _assert_consistent(root, 3)
    log = metadata.read_episode_log(root)
    assert episode_seeds(root) == [0, 1, 2] and log["next_seed"] == 3
    assert [r["interrupted"] for r in log["runs"]] == [True, True, False]
    assert log["splits"] == {"train": [0, 1], "val": [2]}
    # The resumed episode is the one its seed gives.
    ds = _load(root)
    start = int(ds.meta.episodes[2]["dataset_from_index"])
    actions = np.stack([ds[start + i][ACTION_KEY].numpy() for i in range(log["episodes"][2]["length"])])
    np.testing.assert_array_equal(actions, regenerate_episode(root, 2)[ACTION_KEY])

    # Resuming with different recording settings is refused, naming the recorded value.
    with pytest.raises(ValueError, match="recorded with --image_size=32"):
        record(_cfg(root, num_episodes=4, resume=True, image_size=48))
    with pytest.raises(ValueError, match="recorded with --grasp=narrow"):
        record(_cfg(root, num_episodes=4, resume=True, grasp="wide"))
    with pytest.raises(ValueError, match="recorded with --grasp_blind_expert=false"):
        record(_cfg(root, num_episodes=4, resume=True, grasp_blind_expert=True))


def test_a_recording_stopped_before_its_split_holds_a_training_episode_trains_on_all(tmp_path, monkeypatch):
    """One of 3 episodes saved: the last quarter would hold out all of it, so until the recording resumes
    the one episode is for training; the finished dataset gets the split it was recorded for."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = tmp_path / "ds"
    save_episode = LeRobotDataset.save_episode

    def save_and_ctrl_c(self, *args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)  # held back until the episode is on disk
        return save_episode(self, *args, **kwargs)

    monkeypatch.setattr(LeRobotDataset, "save_episode", save_and_ctrl_c)
    with pytest.raises(RecordingInterrupted):
        record(_cfg(root, num_episodes=3, obs_type="state"))
    monkeypatch.setattr(LeRobotDataset, "save_episode", save_episode)
    log = metadata.read_episode_log(root)
    assert log["splits"] == {"train": [0], "val": []} and "--val_fraction=0.0" in log["command"]
    summary = record(_cfg(root, num_episodes=3, obs_type="state", resume=True))
    assert (summary.train_episodes, summary.val_episodes) == ([0, 1], [2])


def test_sigkill_loses_only_episodes_since_the_last_checkpoint(tmp_path, caplog):
    """A recording killed with SIGKILL (no cleanup) is rolled back to its last checkpoint on resume."""
    root = tmp_path / "ds"
    code = (
        "from lerobot_suture.cli import main; "
        f"main(['record', '--repo_id={REPO_ID}', '--root={root}', '--num_episodes=50', '--image_size=32', "
        "'--checkpoint_every=2'])"
    )
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    proc = subprocess.Popen(
        [sys.executable, "-c", code], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    checkpoint = root / metadata.CHECKPOINT_PATH

    def read(path: Path, *keys):
        try:
            value = json.loads(path.read_text())
            for key in keys:
                value = value[key]
            return value
        except (OSError, json.JSONDecodeError, KeyError):
            return None

    def past_a_checkpoint() -> bool:
        """A checkpoint holds 2 or more episodes and another one is on disk past it."""
        episodes = read(checkpoint, "episode_log", "episodes") or []
        return len(episodes) >= 2 and (read(root / "meta" / "info.json", "total_episodes") or 0) > len(
            episodes
        )

    deadline = time.monotonic() + 240
    try:
        # Kill it when an episode is on disk past the checkpoint.
        reached = False
        while not reached and time.monotonic() < deadline and proc.poll() is None:
            reached = past_a_checkpoint()
            if not reached:
                time.sleep(0.02)
        assert proc.poll() is None, proc.stderr.read().decode()[-3000:]
        assert reached, "no episode on disk past a checkpoint within 240 s: the state to kill in never came"
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
        proc.stderr.close()
    assert checkpoint.is_file()  # no cleanup happened
    committed = len(json.loads(checkpoint.read_text())["episode_log"]["episodes"])
    with caplog.at_level(logging.WARNING, logger="lerobot_suture.datasets.record"):
        summary = record(_cfg(root, num_episodes=committed + 2, checkpoint_every=2, resume=True))
    removed = re.search(
        r"rolled back to its last checkpoint, (\d+) episodes \((\d+) unfinished files", caplog.text
    )
    assert removed and int(removed[1]) == committed and int(removed[2]) > 0, caplog.text
    _assert_consistent(root, committed + 2)
    assert episode_seeds(root) == list(range(committed + 2))
    assert summary.added_episodes == 2  # what was past the checkpoint was rolled back and redone
