"""The real `lerobot-eval` command: a saved tiny ensemble on the suture env (needs `lerobot_env_suture`)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

pytest.importorskip("lerobot_env_suture")

from lerobot_policy_ensemble_diffusion.testing import (  # noqa: E402
    fake_dataset_stats,
    save_untrained_policy,
    tiny_config,
)

LEROBOT_EVAL = str(Path(sys.executable).parent / "lerobot-eval")


@pytest.fixture
def saved_policy(tmp_path) -> Path:
    """An (untrained) tiny ensemble saved as `lerobot-train` would: weights, config and processors."""
    torch.manual_seed(0)
    stats = fake_dataset_stats()
    config = tiny_config(num_inference_steps=5, noise_scheduler_type="DDIM")
    return save_untrained_policy(config, stats, tmp_path / "pretrained_model")


def test_lerobot_eval_runs_the_ensemble_on_the_suture_env(saved_policy, tmp_path):
    out = tmp_path / "eval"
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    result = subprocess.run(
        [
            LEROBOT_EVAL,
            f"--policy.path={saved_policy}",
            "--policy.device=cpu",
            "--env.type=suture",
            "--env.cbf.enabled=true",  # the safety filter runs inside lerobot-eval's envs too
            "--eval.n_episodes=1",
            "--eval.batch_size=1",
            f"--output_dir={out}",
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert result.returncode == 0, (result.stdout + result.stderr)[-6000:]
    info = json.loads((out / "eval_info.json").read_text())
    assert info  # per-episode and aggregated metrics written by lerobot-eval
