"""Test session setup: headless rendering and no network, before anything imports MuJoCo or the Hub."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ["HF_HUB_OFFLINE"] = "1"
os.environ.setdefault("WANDB_MODE", "disabled")

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

import lerobot_suture  # noqa: E402,F401  - registers the env ids


@pytest.fixture(scope="session")
def tiny_policy_dir(tmp_path_factory) -> Path:
    """An untrained tiny ensemble saved as `lerobot-train` saves one: weights, config and processors.

    Its statistics come from the scripted expert, so its actions and hold poses are in the right units.
    """
    import numpy as np
    import torch
    from lerobot_policy_ensemble_diffusion.testing import save_untrained_policy, tiny_config

    from lerobot_suture.expert import ScriptedExpert
    from lerobot_suture.rollout_expert import iter_expert_steps
    from lerobot_suture.sim.suture_env import SutureEnv

    env, expert, poses = SutureEnv(obs_type="state"), ScriptedExpert(), []
    for seed in range(2):
        obs, _ = env.reset(seed=seed)
        poses += [step.obs["agent_pos"] for step in iter_expert_steps(env, expert, obs)]
    poses = np.asarray(poses, dtype=np.float64)
    pose_stats = {
        "min": poses.min(0) - 1e-3,
        "max": poses.max(0) + 1e-3,
        "mean": poses.mean(0),
        "std": poses.std(0) + 1e-3,
    }
    image_stats = {
        k: np.full((3, 1, 1), v) for k, v in {"min": 0.0, "max": 1.0, "mean": 0.5, "std": 0.25}.items()
    }
    stats = {
        "observation.state": pose_stats,
        "action": dict(pose_stats),
        "observation.images.endoscope": image_stats,
    }

    torch.manual_seed(0)
    config = tiny_config(n_members=2, num_inference_steps=3, noise_scheduler_type="DDIM")
    return save_untrained_policy(config, stats, tmp_path_factory.mktemp("tiny_policy") / "pretrained_model")
