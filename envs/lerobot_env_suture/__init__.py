"""LeRobot env plugin for lerobot-suture: ``--env.type=suture``."""

from lerobot_env_suture.configuration_suture import SutureEnvConfig

__all__ = ["SutureEnvConfig"]
