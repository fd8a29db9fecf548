"""The PSM's Cartesian controller: pose error -> velocity command -> joint velocities.

Pure functions that compute and return; the env writes the result into MuJoCo. Units: m, rad, s.

Tip-first inverse kinematics, the premise of the CBF's guarantee
----------------------------------------------------------------
The CBF filters only the needle tip's linear velocity and keeps h >= 0 at every physics step as long as
the tip stays within its margin of the straight segment it commanded (``safety/cbf.py``). The plain
solve (:func:`damped_least_squares` on the stacked linear and angular rows) breaks that under a large
commanded rotation: it shares its error between the rows, the env then scales the whole joint command to
the actuator limits, and a rotation that drives a wrist joint into its range stop leaves the solve
counting on a joint that no longer moves; the tip went the other way from the filtered velocity, and
random jaw orientations took it out of the safe set. While a filter is installed the env therefore uses
:func:`tip_first_velocity_ik`:

1. The tip's linear velocity is the primary task, solved on the joints that can move inside a box of
   speed limits and range stops (:func:`joint_velocity_bounds`); a joint that would leave its box is
   fixed at its bound and the others compensate (saturation in the null space).
2. The rotation is the secondary task, solved in the primary task's null space, and only it is scaled to
   fit the box: no rotation can bend the tip's path.
3. If the primary task itself cannot be met inside the box (too few free joints, or near a singularity),
   the tip's velocity is scaled down along its own direction. Zero velocity is always inside the box, so
   such a scale always exists, and the tip then stays on a sub-segment of the filtered one, which is in
   the (convex) tightened set too.

The env re-solves this 10 times per control step with feedback on the tip's distance from where the
segment says it should be, which absorbs the tissue's resistance and the actuators' lag. Why this route
rather than filtering the whole twist or the robust (input-to-state) CBF: it makes the tracking premise
true for any command at its source, leaves nominal commands as they were (a nominal throw's rotation
fits in the null space), and keeps the filter the paper's closed form; the residual tracking error is
measured every step (``CBFActionWrapper``'s ``cbf_segment_deviation``) and by
``benchmarks/cbf_adversary.py`` against the margin.
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


def limit_speed(velocity: np.ndarray, max_speed: float) -> np.ndarray:
    """``velocity`` (3,) scaled down along its own direction to at most ``max_speed`` (same units)."""
    speed = float(np.linalg.norm(velocity))
    return velocity * (max_speed / speed) if speed > max_speed else velocity


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


_RANK_TOLERANCE = 1e-9
"""Singular values (m/rad) below this count as zero in the primary task's null-space projector."""
_PRIMARY_RESIDUAL = 1e-2
"""Largest relative error of the point's velocity accepted from the saturated solve (else: scale down)."""


def joint_velocity_bounds(
    q: np.ndarray, q_low: np.ndarray, q_high: np.ndarray, qdot_max: np.ndarray, lookahead: float
) -> tuple[np.ndarray, np.ndarray]:
    """Joint-velocity box that respects the speed limits and keeps the joints inside their range.

    A joint may move towards a range stop at most ``distance / lookahead``, so it approaches the stop
    geometrically instead of hitting it. Zero is always inside the box (a joint beyond its stop is
    not forced back), so holding still is always feasible.

    Args:
        q: (n,) joint positions (rad or m). q_low, q_high: (n,) range. qdot_max: (n,) speed limits (> 0).
        lookahead: time (s, > 0) over which the distance to a stop may be covered.

    Returns:
        (low (n,), high (n,)) joint-velocity bounds (rad/s or m/s), low <= 0 <= high.
    """
    low = np.minimum(np.maximum(-qdot_max, (q_low - q) / lookahead), 0.0)
    high = np.maximum(np.minimum(qdot_max, (q_high - q) / lookahead), 0.0)
    return low, high


def _largest_fraction(base: np.ndarray, step: np.ndarray, low: np.ndarray, high: np.ndarray) -> float:
    """Largest s in [0, 1] with low <= base + s step <= high (``base`` inside the box)."""
    s = 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        up = np.where(step > 0.0, (high - base) / step, np.inf)
        down = np.where(step < 0.0, (low - base) / step, np.inf)
    s = min(s, float(np.min(up)), float(np.min(down)))
    return max(s, 0.0)


def _null_space(jacobian: np.ndarray) -> np.ndarray:
    """Projector (k, k) onto the null space of ``jacobian`` (m, k)."""
    _, sv, vt = np.linalg.svd(jacobian)
    rank = int(np.sum(sv > _RANK_TOLERANCE))
    rows = vt[:rank]
    return np.eye(jacobian.shape[1]) - rows.T @ rows


def tip_first_velocity_ik(
    jac_linear: np.ndarray,
    jac_angular: np.ndarray,
    v_point: np.ndarray,
    angular: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    linear_damping: float = 1e-3,
    angular_damping: float = 1e-2,
) -> tuple[np.ndarray, float, float]:
    """Joint velocities that give the point ``v_point`` first and the angular velocity as far as they can.

    Args:
        jac_linear: (3, n) linear Jacobian (m/rad) of the controlled point (the needle tip).
        jac_angular: (3, n) angular Jacobian (rad/rad).
        v_point: (3,) desired point velocity (m/s), world frame.
        angular: (3,) desired angular velocity (rad/s), world frame.
        low, high: (n,) joint-velocity bounds with low <= 0 <= high (:func:`joint_velocity_bounds`).
        linear_damping: damping (m) of the primary solve.
        angular_damping: damping (unit-free) of the secondary solve.

    Returns:
        (qdot (n,) inside [low, high], linear_scale in [0, 1], rotation_scale in [0, 1]):
        ``linear_scale`` < 1 when the point's velocity was scaled down along its direction to fit the
        bounds; ``rotation_scale`` is the fraction of the null-space rotation solve kept.
    """
    n = jac_linear.shape[1]
    free = np.ones(n, dtype=bool)
    q_fixed = np.zeros(n)
    primary = None
    for _ in range(n - 2):
        q1 = q_fixed.copy()
        q1[free] += damped_least_squares(jac_linear[:, free], v_point - jac_linear @ q_fixed, linear_damping)
        over = np.maximum(np.maximum(low - q1, q1 - high), 0.0)
        if not np.any(over > 1e-12):
            # A near-singular set of free joints meets the bounds but not the velocity: not accepted.
            if np.linalg.norm(jac_linear @ q1 - v_point) <= _PRIMARY_RESIDUAL * np.linalg.norm(v_point):
                primary = q1
            break
        if free.sum() <= 3:  # no redundancy left to compensate another fixed joint
            break
        j = int(np.argmax(np.where(free, over / np.maximum(high - low, 1e-12), -1.0)))
        q_fixed[j] = min(max(q1[j], low[j]), high[j])
        free[j] = False
    linear_scale = 1.0
    if primary is None:
        # Keep the direction, give up speed: the tip stays on its commanded segment.
        free[:] = True
        q_fixed[:] = 0.0
        q1 = damped_least_squares(jac_linear, v_point, linear_damping)
        linear_scale = _largest_fraction(np.zeros(n), q1, low, high)
        primary = linear_scale * q1
    # Secondary: the rotation, in the null space of the primary task on the free joints.
    projector = _null_space(jac_linear[:, free])
    secondary = np.zeros(n)
    jac_rot_null = jac_angular[:, free] @ projector
    secondary[free] = projector @ damped_least_squares(
        jac_rot_null, angular - jac_angular @ primary, angular_damping
    )
    rotation_scale = _largest_fraction(primary, secondary, low, high)
    return primary + rotation_scale * secondary, linear_scale, rotation_scale
