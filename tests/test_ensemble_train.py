"""The real `lerobot-train` command on a tiny synthetic suture dataset; resume; load; assemble/export."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from lerobot_policy_ensemble_diffusion import EnsembleDiffusionPolicy, assemble_members, export_member
from policy_builders import TINY_POLICY_KWARGS, make_synthetic_dataset
from safetensors import safe_open
from safetensors.torch import load_file, save_file

REPO_ROOT = Path(__file__).resolve().parents[1]
CPU_PRESET = REPO_ROOT / "policies" / "presets" / "cpu.json"
LEROBOT_TRAIN = str(Path(sys.executable).parent / "lerobot-train")
REPO_ID = "local/ensemble_test"


def _policy_overrides(**extra) -> list[str]:
    kwargs = {**TINY_POLICY_KWARGS, "crop_ratio": 1.0, "num_inference_steps": 5, **extra}
    out = []
    for key, value in kwargs.items():
        if isinstance(value, tuple):
            value = "[" + ",".join(str(v) for v in value) + "]"
        out.append(f"--policy.{key}={value}")
    return out


def _run(args: list[str], cwd: Path) -> str:
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1", "TOKENIZERS_PARALLELISM": "false"}
    result = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    output = result.stdout + result.stderr
    assert result.returncode == 0, output[-6000:]
    return output


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("data") / "suture"
    make_synthetic_dataset(root, repo_id=REPO_ID, n_episodes=3, episode_length=30)
    return root


@pytest.fixture(scope="module")
def trained(tmp_path_factory, dataset_root) -> tuple[Path, str]:
    """Two steps of `lerobot-train` from the CPU preset file, shrunk, with the plugin flag."""
    out = tmp_path_factory.mktemp("train") / "run"
    log = _run(
        [
            LEROBOT_TRAIN,
            f"--config_path={CPU_PRESET}",
            "--policy.discover_packages_path=lerobot_policy_ensemble_diffusion",
            *_policy_overrides(),
            f"--dataset.repo_id={REPO_ID}",
            f"--dataset.root={dataset_root}",
            f"--output_dir={out}",
            "--steps=2",
            "--batch_size=2",
            "--num_workers=0",
            "--log_freq=1",
            "--save_freq=2",
        ],
        cwd=out.parent,
    )
    return out, log


def _pretrained(run_dir: Path, step: int) -> Path:
    return run_dir / "checkpoints" / f"{step:06d}" / "pretrained_model"


def test_train_saves_every_member(trained):
    run_dir, log = trained
    model_dir = _pretrained(run_dir, 2)
    config = json.loads((model_dir / "config.json").read_text())
    assert config["type"] == "ensemble_diffusion" and config["n_members"] == 2
    assert config["pretrained_backbone_weights"] is None
    assert config["noise_scheduler_type"] == "DDIM"  # from the preset file
    with safe_open(str(model_dir / "model.safetensors"), framework="pt") as f:
        members = {k.split(".")[1] for k in f.keys() if k.startswith("members.")}  # noqa: SIM118
    assert members == {"0", "1"}
    for name in ("policy_preprocessor.json", "policy_postprocessor.json", "train_config.json"):
        assert (model_dir / name).is_file()
    assert "loss_member_0:" in log and "loss_member_1:" in log


def test_resume_continues_without_plugin_flag(trained, dataset_root):
    run_dir, _ = trained
    before = load_file(str(_pretrained(run_dir, 2) / "model.safetensors"))
    # No --policy.discover_packages_path: the plugin is found by its distribution name.
    _run(
        [
            LEROBOT_TRAIN,
            f"--config_path={_pretrained(run_dir, 2) / 'train_config.json'}",
            "--resume=true",
            "--steps=3",
            f"--dataset.root={dataset_root}",
        ],
        cwd=run_dir.parent,
    )
    state = json.loads(
        (run_dir / "checkpoints" / "000003" / "training_state" / "training_step.json").read_text()
    )
    assert state["step"] == 3
    after = load_file(str(_pretrained(run_dir, 3) / "model.safetensors"))
    assert before.keys() == after.keys()
    assert any(not torch.equal(before[k], after[k]) for k in before if "unet" in k)


def test_load_offline_and_read_mean_and_covariance(trained, dataset_root, monkeypatch):
    from lerobot.datasets import LeRobotDataset
    from lerobot.policies.factory import make_pre_post_processors

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    model_dir = _pretrained(trained[0], 2)
    policy = EnsembleDiffusionPolicy.from_pretrained(model_dir)
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=str(model_dir))
    frame = LeRobotDataset(REPO_ID, root=dataset_root)[0]
    observation = {k: v for k, v in frame.items() if k.startswith("observation.")}
    observation["task"] = frame["task"]
    action = postprocessor(policy.select_action(preprocessor(observation)))  # (1, A) in dataset units
    assert action.shape == (1, 10)
    prediction = policy.last_prediction
    assert prediction.normalized.covariance.shape == (1, 8, 10, 10)
    torch.testing.assert_close(action, prediction.unnormalized.mean[:, prediction.action_steps][:, 0])
    assert torch.isfinite(prediction.score).all()


def _files(directory: Path) -> set[str]:
    return {p.name for p in directory.iterdir()}


def test_assembled_members_equal_the_jointly_trained_ensemble(trained, tmp_path):
    joint = _pretrained(trained[0], 2)
    members = [export_member(joint, n, tmp_path / f"member_{n}") for n in range(2)]
    assert json.loads((members[0] / "config.json").read_text())["type"] == "diffusion"
    joint_config = json.loads((joint / "config.json").read_text())
    # Ensemble-level options are not in the members; the CPU preset's K is passed as a user would.
    samples = joint_config["uncertainty_samples_per_member"]
    assembled = assemble_members(members, tmp_path / "assembled", uncertainty_samples_per_member=samples)

    assert _files(assembled) == _files(joint) - {"train_config.json"}
    assembled_config = json.loads((assembled / "config.json").read_text())
    assert assembled_config == joint_config
    a, b = load_file(str(joint / "model.safetensors")), load_file(str(assembled / "model.safetensors"))
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].dtype == b[k].dtype
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, equal_nan=True)
    for name in _files(assembled) - {"config.json", "model.safetensors"}:
        assert (assembled / name).read_bytes() == (joint / name).read_bytes(), name


def test_assemble_errors_name_the_problem(trained, tmp_path):
    joint = _pretrained(trained[0], 2)
    member = export_member(joint, 0, tmp_path / "m0")
    with pytest.raises(ValueError, match="at least 2 members"):
        assemble_members([member], tmp_path / "out")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        assemble_members([member, tmp_path / "nope"], tmp_path / "out")
    with pytest.raises(ValueError, match="holds a 'ensemble_diffusion' policy"):
        assemble_members([member, joint], tmp_path / "out")

    other = tmp_path / "m1"
    shutil.copytree(member, other)
    config = json.loads((other / "config.json").read_text())
    config["n_action_steps"] = 2
    (other / "config.json").write_text(json.dumps(config))
    with pytest.raises(ValueError, match=r"`n_action_steps` differs \(m0=4, m1=2\)"):
        assemble_members([member, other], tmp_path / "out")

    shutil.rmtree(other)
    shutil.copytree(member, other)
    stats_file = next(other.glob("policy_preprocessor_step_*_normalizer_processor.safetensors"))
    stats = load_file(str(stats_file))
    stats["action.max"] = stats["action.max"] + 1.0
    save_file(stats, str(stats_file))
    with pytest.raises(ValueError, match="normalizes 'action' with different statistics"):
        assemble_members([member, other], tmp_path / "out")

    assemble_members([member, member], tmp_path / "out")  # valid (if pointless)
    with pytest.raises(FileExistsError, match="not empty"):
        assemble_members([member, member], tmp_path / "out")


@pytest.mark.slow
def test_assemble_separately_trained_diffusion_policies(dataset_root, tmp_path):
    """The scale-out route: plain `lerobot-train --policy.type=diffusion --seed=k` jobs, then assemble."""
    member_dirs = []
    member_kwargs = {k: v for k, v in TINY_POLICY_KWARGS.items() if k != "n_members"}
    for seed in (1, 2):
        out = tmp_path / f"member_{seed}"
        args = [
            f"--policy.{k}=" + ("[" + ",".join(map(str, v)) + "]" if isinstance(v, tuple) else str(v))
            for k, v in member_kwargs.items()
        ]
        _run(
            [
                LEROBOT_TRAIN,
                "--policy.type=diffusion",
                "--policy.pretrained_backbone_weights=null",
                "--policy.use_group_norm=true",
                "--policy.push_to_hub=false",
                "--policy.device=cpu",
                *args,
                f"--seed={seed}",
                f"--dataset.repo_id={REPO_ID}",
                f"--dataset.root={dataset_root}",
                f"--output_dir={out}",
                "--steps=2",
                "--batch_size=2",
                "--num_workers=0",
            ],
            cwd=tmp_path,
        )
        member_dirs.append(_pretrained(out, 2))
    ensemble_dir = assemble_members(member_dirs, tmp_path / "ensemble")
    policy = EnsembleDiffusionPolicy.from_pretrained(ensemble_dir)
    a = load_file(str(member_dirs[1] / "model.safetensors"))
    for key, value in a.items():
        torch.testing.assert_close(policy.state_dict()[f"members.1.{key}"], value, rtol=0, atol=0)
