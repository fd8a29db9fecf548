"""The tissue model: where the needle is in the phantom, and how far it strays off its own arc.

Pure numpy. The phantom frame has its origin at the centre of the tissue pad's top surface, z the
surface normal, x the entry->exit direction. A needle moving only along its own arc (rotating about
its centre and axis) slides through the holes it made; any other motion of the needle while in
tissue (its centre moving, or turning about any other axis) cuts and stretches tissue. We measure
that off-arc motion (metres of tissue displacement) and resist it viscously
(:func:`resistance_joint_forces`, which the env applies to the arm).
"""

from __future__ import annotations

import math

import numpy as np

from lerobot_suture.sim.controller import point_velocity
from lerobot_suture.sim.geometry import matrix_from_rotvec, rotation_angle_of

PAD_HALF_SIZE = np.array([0.03, 0.02, 0.005])
"""Half extents of the tissue pad (m), as ``tissue_pad`` in ``assets/scene.xml``; top at z = 0."""

# Viscous resistance to off-arc motion of the needle (N per m/s, N m per rad/s).
TISSUE_DAMPING = 2.0
TISSUE_ROTATIONAL_DAMPING = 0.0001


def inside_pad(points_phantom: np.ndarray) -> np.ndarray:
    """Which points (phantom frame, (..., 3), m) lie inside the tissue pad; bool (...)."""
    p = points_phantom
    return (
        (np.abs(p[..., 0]) <= PAD_HALF_SIZE[0])
        & (np.abs(p[..., 1]) <= PAD_HALF_SIZE[1])
        & (p[..., 2] <= 0.0)
        & (p[..., 2] >= -2.0 * PAD_HALF_SIZE[2])
    )


def surface_crossing(previous: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Point where the segment previous -> current (phantom frame, m) crosses the top surface z = 0."""
    dz = current[2] - previous[2]
    if abs(dz) < 1e-12:
        return current.copy()
    t = min(1.0, max(0.0, -previous[2] / dz))
    return previous + t * (current - previous)


def off_arc_motion(
    centre_before: np.ndarray,
    rotation_before: np.ndarray,
    centre_after: np.ndarray,
    rotation_after: np.ndarray,
    radius: float,
) -> tuple[float, float]:
    """Off-arc motion of the needle between two poses, both relative to the phantom.

    Args:
        centre_before, centre_after: (3,) needle centre in the phantom frame (m).
        rotation_before, rotation_after: (3, 3) needle orientation in the phantom frame.
        radius: needle radius (m), converting off-axis rotation into tissue displacement.

    Returns:
        (translation (m), rotation (m)): the centre's displacement, and ``radius`` times the part
        of the relative rotation angle about axes other than the needle's own axis.
    """
    translation = float(np.linalg.norm(centre_after - centre_before))
    delta = rotation_before.T @ rotation_after  # in the needle's own frame
    angle = rotation_angle_of(delta)
    if angle < 1e-9:
        return translation, 0.0
    axis = np.array([delta[2, 1] - delta[1, 2], delta[0, 2] - delta[2, 0], delta[1, 0] - delta[0, 1]])
    norm = np.linalg.norm(axis)
    off_axis_fraction = math.hypot(axis[0], axis[1]) / norm if norm > 1e-12 else 1.0
    return translation, radius * angle * off_axis_fraction


def _skew(v: np.ndarray) -> np.ndarray:
    """Matrix of ``w -> cross(v, w)``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def arc_target(
    centre: np.ndarray,
    axis: np.ndarray,
    jaw_pos: np.ndarray,
    jaw_rot: np.ndarray,
    point: np.ndarray,
    target_point: np.ndarray,
    max_angle: float = math.pi,
) -> tuple[np.ndarray, np.ndarray]:
    """The jaw pose, on the needle's arc, nearest to a target: the jaw turned about the needle's own axis through
    its centre, the one motion that cuts no tissue, by the angle that brings the driven ``point`` (the needle tip)
    closest to where the target would put it (``target_point``), at most ``max_angle``. World frame; m, rad.

    Args:
        centre: (3,) m the needle's centre; axis: (3,) its axis (any length > 0).
        jaw_pos, jaw_rot: (3,) m, (3, 3) the jaw's pose now.
        point, target_point: (3,) m the driven point now, and where the target pose puts it.
        max_angle: the largest turn (rad) towards it.

    Returns:
        ``(position, rotation)``: the jaw's target on the arc; the pose now where ``point`` lies on the axis.
    """
    n = np.asarray(axis, dtype=np.float64)
    n = n / np.linalg.norm(n)
    now = np.asarray(point, dtype=np.float64) - centre
    wanted = np.asarray(target_point, dtype=np.float64) - centre
    now, wanted = now - (now @ n) * n, wanted - (wanted @ n) * n  # both in the plane of the turn
    if now @ now < 1e-18 or wanted @ wanted < 1e-18:
        return np.array(jaw_pos, dtype=np.float64), np.array(jaw_rot, dtype=np.float64)
    angle = math.atan2(float(np.cross(now, wanted) @ n), float(now @ wanted))
    angle = float(np.clip(angle, -max_angle, max_angle))
    turn = matrix_from_rotvec(angle * n)
    return centre + turn @ (np.asarray(jaw_pos, dtype=np.float64) - centre), turn @ jaw_rot


def resistance_joint_forces(
    centre: np.ndarray,
    axis: np.ndarray,
    point: np.ndarray,
    v_point: np.ndarray,
    angular: np.ndarray,
    jac_linear: np.ndarray,
    jac_angular: np.ndarray,
) -> np.ndarray:
    """Generalized joint forces resisting the off-arc motion of a needle in tissue (world frame).

    Args:
        centre: (3,) needle centre (m), where the resisting force acts.
        axis: (3,) unit needle axis; turning about it slides the needle along its own arc, unresisted.
        point: (3,) point where the Jacobians were taken (the needle tip, m).
        v_point: (3,) commanded velocity of ``point`` (m/s).
        angular: (3,) commanded angular velocity (rad/s).
        jac_linear: (3, J) linear Jacobian of the J joints at ``point``.
        jac_angular: (3, J) angular Jacobian of the J joints.

    Returns:
        (J,) joint forces (N or N m).
    """
    v_centre = point_velocity(v_point, angular, point, centre)
    w_off = angular - (angular @ axis) * axis
    force = -TISSUE_DAMPING * v_centre
    torque = -TISSUE_ROTATIONAL_DAMPING * w_off
    # The force acts at the needle centre: shift the linear Jacobian from the control point.
    jac_centre = jac_linear - _skew(centre - point) @ jac_angular
    return jac_centre.T @ force + jac_angular.T @ torque
