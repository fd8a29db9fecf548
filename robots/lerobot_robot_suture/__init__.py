"""LeRobot robot plugin: ``--robot.type=suture_sim``, the MuJoCo needle-insertion scene of ``lerobot_suture``
behind LeRobot's ``Robot`` interface, and ``--teleop.type=suture_keyboard`` / ``suture_gamepad``, LeRobot's
keyboard and gamepad driving it.

LeRobot's commands import this package at start-up (``register_third_party_plugins``: the distribution's
name starts with ``lerobot_robot_``), which registers the three types and the ``suture_cbf`` robot-action processor step.
"""

from .cbf_step import REGISTRATION_FEATURES, SutureCBFStep
from .config_suture_sim import CAMERA, POSE_FEATURES, SutureSimConfig
from .config_suture_teleop import SutureGamepadConfig, SutureKeyboardConfig
from .suture_sim import FPS, SutureSim
from .suture_teleop import SutureGamepad, SutureKeyboard

__all__ = [
    "CAMERA",
    "FPS",
    "POSE_FEATURES",
    "REGISTRATION_FEATURES",
    "SutureCBFStep",
    "SutureGamepad",
    "SutureGamepadConfig",
    "SutureKeyboard",
    "SutureKeyboardConfig",
    "SutureSim",
    "SutureSimConfig",
]
