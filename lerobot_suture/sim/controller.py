"""The PSM's Cartesian controller: pose error -> velocity command -> joint velocities.

Pure functions that compute and return; the env writes the result into MuJoCo. Units: m, rad, s.
"""

from __future__ import annotations

import numpy as np

from lerobot_suture.sim.geometry import cross3, rotvec_from_matrix


def pose_velocity_command(
    position: np.ndarray,
    rotation: np.ndarray,
    target_position: np.ndarray,
    target_rotation: np.ndarray,
    time_to_target: float,
    max_linear_speed: float,
    max_angular_speed: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Cartesian twist that reaches the target pose in ``time_to_target`` seconds, speed-limited.

    Returns:
        (linear velocity (3,) m/s of the controlled point, angular velocity (3,) rad/s), world frame.
    """
    linear = (target_position - position) / time_to_target
    speed = float(np.linalg.norm(linear))
    if speed > max_linear_speed:
        linear *= max_linear_speed / speed
    angular = rotvec_from_matrix(target_rotation @ rotation.T) / time_to_target
    rate = float(np.linalg.norm(angular))
    if rate > max_angular_speed:
        angular *= max_angular_speed / rate
    return linear, angular


def point_velocity(linear: np.ndarray, angular: np.ndarray, origin: np.ndarray, point: np.ndarray):
    """Velocity (3,) m/s of ``point`` rigidly attached to a frame at ``origin`` moving with the twist."""
    return linear + cross3(angular, point - origin)


def damped_least_squares(jacobian: np.ndarray, twist: np.ndarray, damping: float) -> np.ndarray:
    """Joint velocities q_dot = J^T (J J^T + damping^2 I)^-1 twist (differential IK).

    Args:
        jacobian: (6, n) stacked linear (rows 0-2) and angular (rows 3-5) Jacobian.
        twist: (6,) desired linear (m/s) and angular (rad/s) velocity.
        damping: damping factor (unitless in the mixed m/rad metric); trades accuracy near
            singularities for bounded joint speeds.
    """
    jjt = jacobian @ jacobian.T
    jjt[np.diag_indices_from(jjt)] += damping**2
    return jacobian.T @ np.linalg.solve(jjt, twist)
