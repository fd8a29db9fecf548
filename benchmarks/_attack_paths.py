"""The path an attack or cost benchmark runs on, by name: the env path here, the robot path from the robot plugin
(imported only when asked for, so the env path needs no robot plugin). Not a benchmark itself."""

from __future__ import annotations

from lerobot_suture.experiments.attack_episodes import CONDITIONS, EnvPath
from lerobot_suture.safety.cbf_config import CBFConfig


def make_path(path: str, condition: str, cbf: CBFConfig, env_kwargs: dict | None = None):
    """``EnvPath`` or ``RobotPath`` in ``condition`` (``attack_episodes.CONDITIONS``) with the filter ``cbf``;
    ``env_kwargs``: more ``SutureEnv`` arguments on the env path."""
    if path == "env":
        return EnvPath(CONDITIONS[condition], cbf, **(env_kwargs or {}))
    from lerobot_robot_suture.attacks import RobotPath

    return RobotPath(CONDITIONS[condition], cbf)
