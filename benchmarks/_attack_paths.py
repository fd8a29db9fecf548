"""The path an attack or cost benchmark runs on, by name: the env path here, the robot path from the robot plugin
(imported only when asked for, so the env path needs no robot plugin). Not a benchmark itself."""

from __future__ import annotations

from lerobot_suture.experiments.attack_episodes import CONDITIONS, EnvPath
from lerobot_suture.safety.cbf_config import CBFConfig


def make_path(path: str, condition: str, cbf: CBFConfig, env_kwargs: dict | None = None):
    """``EnvPath`` or ``RobotPath`` in ``condition`` (``attack_episodes.CONDITIONS``) with the filter ``cbf``;
    ``env_kwargs``: more ``SutureEnv`` arguments on the env path (a policy's observations); on the robot path
    its ``image_size`` only, since the arm reports no simulator state."""
    env_kwargs = env_kwargs or {}
    if path == "env":
        return EnvPath(CONDITIONS[condition], cbf, **env_kwargs)
    from lerobot_robot_suture.attacks import RobotPath

    if env_kwargs.get("obs_type", "pixels_agent_pos") != "pixels_agent_pos":
        raise ValueError(
            f"The robot path reports the endoscope and the pose only; the policy reads {env_kwargs['obs_type']}."
        )
    return RobotPath(
        CONDITIONS[condition], cbf, **({"image_size": env_kwargs["image_size"]} if env_kwargs else {})
    )
