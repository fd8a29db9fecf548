"""Gymnasium registration, from one table, and the factory it points to."""

from __future__ import annotations

import gymnasium as gym

ENV_ID = "lerobot_suture/NeedleInsertion-v0"
MAX_EPISODE_STEPS = 100
"""10 s at the 10 Hz control rate; the expert needs about 6 s."""

_ENVS = {
    ENV_ID: ("lerobot_suture.registration:make_suture_env", MAX_EPISODE_STEPS),
}


def make_suture_env(cbf=None, **kwargs) -> gym.Env:
    """A :class:`~lerobot_suture.sim.suture_env.SutureEnv`, behind the CBF safety filter when asked.

    Args:
        cbf: None (no filter), or a :class:`~lerobot_suture.safety.cbf_config.CBFConfig` (or its fields
            as a dict); the env is then wrapped in
            :class:`~lerobot_suture.safety.cbf_wrapper.CBFActionWrapper`.
        **kwargs: the env's own arguments (see its docstring).
    """
    from lerobot_suture.sim.suture_env import SutureEnv

    env = SutureEnv(**kwargs)
    if cbf is None:
        return env
    from lerobot_suture.safety.cbf_config import CBFConfig
    from lerobot_suture.safety.cbf_wrapper import CBFActionWrapper

    if isinstance(cbf, dict):
        cbf = CBFConfig(**cbf)
    if not isinstance(cbf, CBFConfig):
        raise ValueError(
            f"`cbf` must be a CBFConfig, a dict of its fields, or None. Got {type(cbf).__name__}."
        )
    return CBFActionWrapper(env, cbf)


def register_envs() -> None:
    for env_id, (entry_point, max_steps) in _ENVS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry_point, max_episode_steps=max_steps)
