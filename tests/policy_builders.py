#!/usr/bin/env python

# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.
"""Small builders shared by the tests and the benchmarks (``benchmarks/_policy_builders.py``): suture-shaped
features, a tiny synthetic LeRobotDataset on disk, tiny ensemble configs and random normalized observations.

The suture env/dataset features: `observation.images.endoscope` (3, 96, 96), `observation.state` (10,),
`action` (10,), `observation.needle_keypoints` (6,), 10 fps.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_STATE
from lerobot_policy_ensemble_diffusion.configuration_ensemble_diffusion import (
    NEEDLE_KEYPOINTS_KEY,
    EnsembleDiffusionConfig,
)

IMAGE_KEY = "observation.images.endoscope"
STATE_DIM = 10
ACTION_DIM = 10
NEEDLE_KEYPOINTS_DIM = 6  # x and y of the needle's tip, middle and tail in the image
IMAGE_SIZE = 96
FPS = 10

SUTURE_DATASET_FEATURES = {
    IMAGE_KEY: {
        "dtype": "image",
        "shape": (IMAGE_SIZE, IMAGE_SIZE, 3),
        "names": ["height", "width", "channels"],
    },
    OBS_STATE: {"dtype": "float32", "shape": (STATE_DIM,), "names": None},
    ACTION: {"dtype": "float32", "shape": (ACTION_DIM,), "names": None},
}

SUTURE_INPUT_FEATURES = {
    IMAGE_KEY: PolicyFeature(type=FeatureType.VISUAL, shape=(3, IMAGE_SIZE, IMAGE_SIZE)),
    OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,)),
}
SUTURE_OUTPUT_FEATURES = {ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(ACTION_DIM,))}

# A few-second ensemble: 32x32 images, a two-level U-Net, 10 diffusion steps.
TINY_POLICY_KWARGS = {
    "n_members": 2,
    "n_obs_steps": 2,
    "horizon": 8,
    "n_action_steps": 4,
    "drop_n_last_frames": 3,
    "resize_shape": (32, 32),
    "down_dims": (16, 32),
    "diffusion_step_embed_dim": 16,
    "spatial_softmax_num_keypoints": 8,
    "num_train_timesteps": 10,
}


def tiny_policy_cli_args() -> list[str]:
    """`TINY_POLICY_KWARGS` as `lerobot-train` arguments (plus the offline/CPU flags)."""
    args = []
    for key, value in TINY_POLICY_KWARGS.items():
        if isinstance(value, tuple):
            value = "[" + ",".join(str(v) for v in value) + "]"
        args.append(f"--policy.{key}={value}")
    return [
        "--policy.type=ensemble_diffusion",
        "--policy.pretrained_backbone_weights=null",
        "--policy.push_to_hub=false",
        "--policy.device=cpu",
        *args,
    ]


def tiny_config(**overrides) -> EnsembleDiffusionConfig:
    """A tiny CPU ensemble config with the suture features filled in."""
    kwargs = {
        **TINY_POLICY_KWARGS,
        "device": "cpu",
        "input_features": dict(SUTURE_INPUT_FEATURES),
        "output_features": dict(SUTURE_OUTPUT_FEATURES),
        **overrides,
    }
    return EnsembleDiffusionConfig(**kwargs)


def save_untrained_policy(
    config: EnsembleDiffusionConfig, stats: dict[str, dict[str, np.ndarray]], directory: str | Path
) -> Path:
    """An untrained ensemble saved as `lerobot-train` saves one: weights, config and pre/post-processors.

    Seed torch first for reproducible weights. Returns `directory`.
    """
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot_policy_ensemble_diffusion.modeling_ensemble_diffusion import EnsembleDiffusionPolicy

    directory = Path(directory)
    EnsembleDiffusionPolicy(config, dataset_stats=stats).save_pretrained(directory)
    for pipeline in make_pre_post_processors(config, dataset_stats=stats):
        pipeline.save_pretrained(directory)
    return directory


def expert_dataset_stats(n_seeds: int = 2) -> dict[str, dict[str, np.ndarray]]:
    """Statistics of the scripted expert's poses (state and action) over `n_seeds` throws, with images in
    [0, 1]: an untrained policy normalized with them acts in metres, inside the workspace."""
    from lerobot_suture.expert import ScriptedExpert, iter_expert_steps
    from lerobot_suture.sim.suture_env import SutureEnv

    env, expert, poses = SutureEnv(obs_type="state"), ScriptedExpert(), []
    for seed in range(n_seeds):
        obs, _ = env.reset(seed=seed)
        poses += [step.obs["agent_pos"] for step in iter_expert_steps(env, expert, obs)]
    env.close()
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
    return {OBS_STATE: pose_stats, ACTION: dict(pose_stats), IMAGE_KEY: image_stats}


def save_untrained_expert_policy(directory: str | Path, seed: int = 0, **config_overrides) -> Path:
    """An untrained tiny ensemble (`tiny_config(**config_overrides)`, torch seeded with `seed`) normalized
    with the scripted expert's statistics, saved to `directory` as `lerobot-train` saves one: its actions
    and hold poses are in metres, and it knows nothing of the task."""
    stats = expert_dataset_stats(n_seeds=2)
    torch.manual_seed(seed)
    return save_untrained_policy(tiny_config(**config_overrides), stats, directory)


def tiny_act_config(input_features: dict | None = None):
    """A tiny CPU LeRobot ACT config (chunks of 8, 4 executed) with the suture features, or ``input_features``."""
    from lerobot.policies.act.configuration_act import ACTConfig

    return ACTConfig(
        input_features=dict(input_features or SUTURE_INPUT_FEATURES),
        output_features=dict(SUTURE_OUTPUT_FEATURES),
        chunk_size=8,
        n_action_steps=4,
        pretrained_backbone_weights=None,
        dim_model=32,
        n_heads=2,
        dim_feedforward=64,
        n_encoder_layers=1,
        n_vae_encoder_layers=1,
        device="cpu",
    )


def save_untrained_act_policy(directory: str | Path, seed: int = 0) -> Path:
    """An untrained tiny LeRobot ACT (chunks of 8, 4 executed) with the scripted expert's statistics, saved to
    `directory` as `lerobot-train` saves one."""
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    stats = expert_dataset_stats(n_seeds=2)
    config = tiny_act_config()
    torch.manual_seed(seed)
    directory = Path(directory)
    ACTPolicy(config).save_pretrained(directory)
    for pipeline in make_pre_post_processors(config, dataset_stats=stats):
        pipeline.save_pretrained(directory)
    return directory


def fake_dataset_stats(seed: int = 0) -> dict[str, dict[str, np.ndarray]]:
    """Dataset-like statistics for the suture features (enough for MIN_MAX / MEAN_STD normalization)."""
    rng = np.random.default_rng(seed)
    stats = {}
    for key, dim in ((OBS_STATE, STATE_DIM), (ACTION, ACTION_DIM)):
        low = rng.uniform(-1.0, 0.0, dim).astype(np.float32)
        high = low + rng.uniform(0.5, 2.0, dim).astype(np.float32)
        stats[key] = {"min": low, "max": high, "mean": (low + high) / 2, "std": (high - low) / 4}
    stats[IMAGE_KEY] = {
        "mean": np.full((3, 1, 1), 0.5, np.float32),
        "std": np.full((3, 1, 1), 0.25, np.float32),
        "min": np.zeros((3, 1, 1), np.float32),
        "max": np.ones((3, 1, 1), np.float32),
    }
    return stats


def random_observation(
    config: EnsembleDiffusionConfig, batch_size: int = 1, n_steps: int | None = None, seed: int = 0
) -> dict[str, torch.Tensor]:
    """A normalized observation batch: (B, S, ...) with S = `n_steps` (default n_obs_steps), or (B, ...)
    when `n_steps` is 0 (one env step, as `select_action` receives it)."""
    g = torch.Generator().manual_seed(seed)
    s = config.n_obs_steps if n_steps is None else n_steps
    lead = (batch_size,) if s == 0 else (batch_size, s)
    batch = {OBS_STATE: torch.randn(*lead, config.robot_state_feature.shape[0], generator=g)}
    for key, ft in config.image_features.items():
        batch[key] = torch.randn(*lead, *ft.shape, generator=g)
    return batch


def make_synthetic_dataset(
    root: str | Path,
    repo_id: str = "local/ensemble_test",
    n_episodes: int = 3,
    episode_length: int = 30,
    seed: int = 0,
    needle_keypoints: bool = False,
):
    """Write a tiny suture-shaped LeRobotDataset (images stored as PNG, no video) and return it.

    State and action follow smooth random sinusoids; the image is a smooth gradient plus a moving square, so
    that the data is learnable but meaningless. With `needle_keypoints`, the dataset also holds
    `observation.needle_keypoints` (6,): the square's top-left corner, centre and bottom-right corner in the
    image, (x right, y down) in [-1, 1], as `lerobot-suture record` writes the needle's tip, middle and tail.
    """
    from lerobot.datasets import LeRobotDataset

    rng = np.random.default_rng(seed)
    features = dict(SUTURE_DATASET_FEATURES)
    if needle_keypoints:
        features[NEEDLE_KEYPOINTS_KEY] = {"dtype": "float32", "shape": (NEEDLE_KEYPOINTS_DIM,), "names": None}
    dataset = LeRobotDataset.create(repo_id=repo_id, root=root, fps=FPS, features=features, use_videos=False)
    yy, xx = np.mgrid[0:IMAGE_SIZE, 0:IMAGE_SIZE] / IMAGE_SIZE
    for _ in range(n_episodes):
        phase = rng.uniform(0, 2 * np.pi, STATE_DIM)
        freq = rng.uniform(0.05, 0.2, STATE_DIM)
        for t in range(episode_length):
            state = np.sin(phase + freq * t).astype(np.float32)
            action = np.sin(phase + freq * (t + 1)).astype(np.float32)
            image = np.stack([xx, yy, 0.5 * (xx + yy)], axis=-1)
            cx = int((0.5 + 0.4 * np.sin(phase[0] + freq[0] * t)) * (IMAGE_SIZE - 12))
            image[cx : cx + 12, cx : cx + 12] = 1.0
            frame = {
                IMAGE_KEY: (image * 255).astype(np.uint8),
                OBS_STATE: state,
                ACTION: action,
                "task": "insert the needle",
            }
            if needle_keypoints:
                corners = np.array([cx, cx + 6, cx + 12], dtype=np.float32)  # the square lies on the diagonal
                frame[NEEDLE_KEYPOINTS_KEY] = np.repeat(corners / IMAGE_SIZE * 2 - 1, 2)  # (x, y) per point
            dataset.add_frame(frame)
        dataset.save_episode()
    dataset.finalize()
    return dataset


class ExpertAsPolicy:
    """The scripted expert in a policy runner's place (``reset``, ``act_batch``, ``policy``) for one env: episodes
    whose control flow (handovers, gates, the CBF's premise) is under test, not a policy's skill."""

    def __init__(self, env):
        from lerobot_suture.expert import ScriptedExpert

        self.env, self.policy, self.expert = env, self, ScriptedExpert()

    def reset(self, seeds=None):
        self.expert.reset(self.env)

    def act_batch(self, observations, tasks=None):
        return [self.expert.act(self.env)]
