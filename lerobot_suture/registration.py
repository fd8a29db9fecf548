"""Gymnasium registration, from one table."""

from __future__ import annotations

import gymnasium as gym

ENV_ID = "lerobot_suture/NeedleInsertion-v0"
MAX_EPISODE_STEPS = 100
"""10 s at the 10 Hz control rate; the expert needs about 6 s."""

_ENVS = {
    ENV_ID: ("lerobot_suture.sim.suture_env:SutureEnv", MAX_EPISODE_STEPS),
}


def register_envs() -> None:
    for env_id, (entry_point, max_steps) in _ENVS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry_point, max_episode_steps=max_steps)
