"""A teleoperator's command as a target pose of the needle holder: pure functions, no device.

LeRobot's end-effector teleoperators (``KeyboardEndEffectorTeleop``, ``GamepadTeleop``) emit
``{"delta_x", "delta_y", "delta_z", "gripper"}``: a translation command per axis in [-1, 1] and a
gripper command (0 close, 1 stay, 2 open). The suture env's action is an absolute target pose
(position, two rotation columns, jaw; see ``SutureEnv``), so the surgeon's command is integrated into a
target that starts at the measured pose when the surgeon takes over:

- position += ``translation_speed * control_dt * (delta_x, delta_y, delta_z)``, in the world frame (m),
  then clipped to the workspace (``task.WORKSPACE_LOW`` / ``WORKSPACE_HIGH``);
- rotation  = rotation @ exp(``rotation_speed * control_dt * (wx, wy, wz)``), about the jaw's own axes
  (rad); the teleoperators have no rotation command, so the surgeon adapters add one (keys, a stick);
- jaw: close -> 1 (closed), open -> 0 (open, releases the needle), stay -> unchanged.

Holding the target, not re-reading the measured pose each step, keeps the arm still when the surgeon
commands nothing (a measured pose sags under the tissue's forces; a held target does not drift).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lerobot_suture.sim.geometry import matrix_from_rot6, matrix_from_rotvec, pose_vector
from lerobot_suture.sim.task import CONTROL_DT, WORKSPACE_HIGH, WORKSPACE_LOW

GRIPPER_CLOSE, GRIPPER_STAY, GRIPPER_OPEN = 0, 1, 2
"""LeRobot's gripper commands (``teleop_gamepad.GripperAction``; the keyboard uses the same values)."""
JAW_CLOSED, JAW_OPEN = 1.0, 0.0


@dataclass
class TeleopMappingConfig:
    """How far one control step of a full command moves the needle holder.

    Args:
        translation_speed: jaw-tip speed at a full translation command (m/s); 5 mm/s moves 0.5 mm per
            10 Hz step, a fraction of the 8 mm safe set around the wound.
        rotation_speed: jaw turning rate at a full rotation command (rad/s).
        control_dt: control period the command is held for (s); the env's, 0.1 s.
    """

    translation_speed: float = 0.005
    rotation_speed: float = 0.3
    control_dt: float = CONTROL_DT

    def __post_init__(self):
        for name, high in (("translation_speed", 0.1), ("rotation_speed", 5.0), ("control_dt", 1.0)):
            value = getattr(self, name)
            if not (0 < value <= high and math.isfinite(value)):
                raise ValueError(f"`{name}` must be in (0, {high}]. Got {value}.")


def translation_command(teleop_action: dict) -> np.ndarray:
    """(3,) translation command in [-1, 1] from a teleoperator action dict (missing axes are 0)."""
    command = np.array([float(teleop_action.get(f"delta_{a}", 0.0)) for a in "xyz"])
    if not np.all(np.isfinite(command)):
        raise ValueError(f"The teleoperator's deltas must be finite. Got {command}.")
    return np.clip(command, -1.0, 1.0)


def jaw_target(jaw: float, gripper: float | None) -> float:
    """The jaw target after a LeRobot gripper command (None or 1 keeps it)."""
    if gripper is None:
        return jaw
    gripper = int(round(float(gripper)))
    if gripper == GRIPPER_CLOSE:
        return JAW_CLOSED
    if gripper == GRIPPER_OPEN:
        return JAW_OPEN
    return jaw


def initial_target(measured_pose: np.ndarray) -> np.ndarray:
    """(10,) target at a takeover: the measured pose, its jaw rounded to closed or open.

    The measured jaw reads about 0.88 while it holds the needle (the wire keeps it apart); commanding
    that reading would loosen the grip, so a closed-ish jaw is commanded closed.
    """
    pose = np.asarray(measured_pose, dtype=np.float64).copy()
    pose[9] = JAW_CLOSED if pose[9] >= 0.5 else JAW_OPEN
    return pose


def step_target(
    target: np.ndarray,
    teleop_action: dict,
    rotation: np.ndarray | None,
    config: TeleopMappingConfig,
) -> np.ndarray:
    """The next (10,) target pose after one control step of a surgeon's command.

    Args:
        target: (10,) current target: position (m, world), two rotation columns, jaw.
        teleop_action: the teleoperator's action dict (``delta_x/y/z`` in [-1, 1], optional ``gripper``).
        rotation: (3,) rotation command in [-1, 1] about the jaw's x, y, z axes, or None (no rotation).
        config: speeds and control period.

    Returns:
        (10,) float64 target, its position inside the workspace and its rotation orthonormal.
    """
    target = np.asarray(target, dtype=np.float64)
    dt = config.control_dt
    position = np.clip(
        target[:3] + config.translation_speed * dt * translation_command(teleop_action),
        WORKSPACE_LOW,
        WORKSPACE_HIGH,
    )
    rotation_matrix = matrix_from_rot6(target[3:9])
    if rotation is not None:
        command = np.clip(np.asarray(rotation, dtype=np.float64), -1.0, 1.0)
        if not np.all(np.isfinite(command)):
            raise ValueError(f"The rotation command must be finite. Got {rotation}.")
        rotation_matrix = rotation_matrix @ matrix_from_rotvec(config.rotation_speed * dt * command)
    jaw = jaw_target(float(target[9]), teleop_action.get("gripper"))
    return pose_vector(position, rotation_matrix, jaw)


def env_action(target: np.ndarray) -> np.ndarray:
    """(10,) float32 env action of a target pose."""
    return np.asarray(target, dtype=np.float32)
