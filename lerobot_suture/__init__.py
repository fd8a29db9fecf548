"""lerobot-suture: safe, uncertainty-aware learning of robotic needle insertion for LeRobot.

Importing the package registers the Gymnasium environment ``lerobot_suture/NeedleInsertion-v0``.
"""

from lerobot_suture.sim.rendering import select_gl_backend

select_gl_backend()

from lerobot_suture.registration import ENV_ID, register_envs  # noqa: E402

register_envs()

__all__ = ["ENV_ID", "register_envs"]
__version__ = "0.1.0"
