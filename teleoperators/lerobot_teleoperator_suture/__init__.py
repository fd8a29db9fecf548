"""LeRobot teleoperator plugin: ``--teleop.type=suture_keyboard`` / ``suture_gamepad`` (LeRobot's keyboard and
gamepad) and ``suture_scripted`` (a scripted surgeon), driving the ``suture_sim`` arm of ``lerobot_robot_suture``
with target poses.

LeRobot's commands import this package at start-up (``register_third_party_plugins``: the distribution's name
starts with ``lerobot_teleoperator_``), which registers the teleoperator types.
"""

from .config_suture_teleop import SutureGamepadConfig, SutureKeyboardConfig, SutureScriptedConfig
from .suture_teleop import SutureGamepad, SutureKeyboard, SutureScripted

__all__ = [
    "SutureGamepad",
    "SutureGamepadConfig",
    "SutureKeyboard",
    "SutureKeyboardConfig",
    "SutureScripted",
    "SutureScriptedConfig",
]
