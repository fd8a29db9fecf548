"""LeRobot robot plugin: ``--robot.type=suture_sim``, the MuJoCo needle-insertion scene of ``lerobot_suture``
behind LeRobot's ``Robot`` interface. The teleoperators that drive it are a plugin of their own,
``lerobot_teleoperator_suture``.

LeRobot's commands import this package at start-up (``register_third_party_plugins``: the distribution's
name starts with ``lerobot_robot_``), which registers the robot type and the ``suture_cbf`` robot-action
processor step. Inside ``lerobot-rollout`` (``lerobot.rollout`` is imported before plugins are) it also
registers the ``gated_dagger`` strategy (:mod:`.rollout_seam`); elsewhere, ``import lerobot_robot_suture.rollout_seam``.
"""

import sys

from .cbf_step import REGISTRATION_FEATURES, SutureCBFStep
from .config_suture_sim import CAMERA, POSE_FEATURES, SutureSimConfig
from .suture_sim import FPS, SutureSim

if "lerobot.rollout" in sys.modules:
    from . import rollout_seam  # noqa: F401  (installs the strategies)

__all__ = [
    "CAMERA",
    "FPS",
    "POSE_FEATURES",
    "REGISTRATION_FEATURES",
    "SutureCBFStep",
    "SutureSim",
    "SutureSimConfig",
]
