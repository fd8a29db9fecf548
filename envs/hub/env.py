"""EnvHub entry point: the `lerobot_suture` needle-insertion env for ``make_env("<user>/<repo>")``.

LeRobot downloads this file from a Hub repository and calls its ``make_env``::

    from lerobot.envs.factory import make_env

    envs = make_env("<user>/<repo>", n_envs=4, use_async_envs=True, trust_remote_code=True)
    vec_env = envs["suture"][0]

It installs nothing: the simulation lives in the `lerobot_suture` package, which must be installed
(``pip install lerobot_suture``). Defaults are those of LeRobot's env type ``suture``.
"""

from __future__ import annotations

import functools
from typing import Any

import gymnasium as gym

SUITE = "suture"
# "module:id" makes gym.make import `lerobot_suture` (which registers the id) in every async
# worker: this file is not importable there, so the env factory must not depend on it.
GYM_ID = "lerobot_suture:lerobot_suture/NeedleInsertion-v0"
# The same as `SutureEnvConfig().gym_kwargs` (envs/lerobot_env_suture/configuration_suture.py).
DEFAULT_GYM_KWARGS: dict[str, Any] = {
    "obs_type": "pixels_agent_pos",
    "image_size": 96,
    "render_mode": "rgb_array",
    "render_size": 256,
    "scenario": "nominal",
    "scenario_onset_step": None,
    "scenario_magnitude": None,
    "max_episode_steps": 100,
    "cbf": None,
}


def _require_lerobot_suture() -> None:
    try:
        import lerobot_suture  # noqa: F401  - registers the gym id
    except ModuleNotFoundError as e:
        if e.name != "lerobot_suture":
            raise
        raise ModuleNotFoundError(
            "This Hub env runs the needle-insertion simulation of the `lerobot_suture` package, which is "
            "not installed. Install it with `pip install lerobot_suture` (or `pip install -e .` in a clone "
            "of the lerobot-suture repository), then call make_env again."
        ) from e


def make_env(
    n_envs: int = 1, use_async_envs: bool = False, cfg: Any = None
) -> dict[str, dict[int, gym.vector.VectorEnv]]:
    """``{"suture": {0: vector_env}}`` of ``n_envs`` needle-insertion envs.

    Args:
        n_envs: number of envs in the vector env (>= 1).
        use_async_envs: one subprocess per env (``AsyncVectorEnv``, forkserver) when ``n_envs > 1``;
            otherwise ``SyncVectorEnv``.
        cfg: the ``EnvConfig`` LeRobot passes when it was given one (e.g. a ``HubEnvConfig``); its
            ``gym_kwargs`` override ``DEFAULT_GYM_KWARGS`` (``image_size``, ``scenario``, ...).
    """
    if isinstance(n_envs, bool) or not isinstance(n_envs, int) or n_envs < 1:
        raise ValueError(f"`n_envs` must be an integer >= 1. Got {n_envs!r}.")
    _require_lerobot_suture()
    kwargs = {**DEFAULT_GYM_KWARGS, **(dict(cfg.gym_kwargs) if cfg is not None else {})}
    disable_env_checker = getattr(cfg, "disable_env_checker", True)
    env_fn = functools.partial(gym.make, GYM_ID, disable_env_checker=disable_env_checker, **kwargs)
    # As LeRobot builds its own env types (EnvConfig.create_envs): no env checker, SAME_STEP autoreset
    # (lerobot-eval reads `final_info`), forkserver workers.
    if use_async_envs and n_envs > 1:
        vec = gym.vector.AsyncVectorEnv(
            [env_fn] * n_envs, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP, context="forkserver"
        )
    else:
        vec = gym.vector.SyncVectorEnv([env_fn] * n_envs, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
    return {SUITE: {0: vec}}
