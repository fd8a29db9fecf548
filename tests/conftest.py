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
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot_policy_ensemble_diffusion import EnsembleDiffusionPolicy
    from lerobot_policy_ensemble_diffusion.testing import tiny_config

    from lerobot_suture.expert import ScriptedExpert
    from lerobot_suture.rollout_expert import run_expert_episode  # noqa: F401 - env registered
    from lerobot_suture.sim.suture_env import SutureEnv

    env, expert, poses = SutureEnv(obs_type="state"), ScriptedExpert(), []
    for seed in range(2):
        obs, _ = env.reset(seed=seed)
        expert.reset(env)
        done = False
        while not done:
            poses.append(obs["agent_pos"])
            obs, _, done, _, _ = env.step(expert.act(env))
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
    policy = EnsembleDiffusionPolicy(config, dataset_stats=stats)
    directory = tmp_path_factory.mktemp("tiny_policy") / "pretrained_model"
    policy.save_pretrained(directory)
    preprocessor, postprocessor = make_pre_post_processors(config, dataset_stats=stats)
    preprocessor.save_pretrained(directory)
    postprocessor.save_pretrained(directory)
    return directory
