"""The registered wound's motion, from successive registrations: how its points move, how fast, how it accelerates.

Tissue moves (breathing, heartbeat, a surgeon's other hand), and the safe set moves with it. The guard filters the
tip's motion relative to the wound's (:class:`WoundMotion.point_velocity`) and checks the motion against the
declared bounds (``CBFConfig.tissue_speed_max``, ``tissue_acceleration_max``). Pure numpy. Units: m, s.
"""

from __future__ import annotations

import numpy as np


def point_velocity(previous: tuple, current: tuple, point: np.ndarray, dt: float) -> np.ndarray:
    """Velocity (3,) m/s of the wound's material point now at ``point`` (3,) m.

    Args:
        previous, current: (centre (3,) m, world-from-wound rotation (3, 3)) of two registrations ``dt`` s apart.
    """
    c0, r0 = previous
    c1, r1 = current
    was = c0 + r0 @ (r1.T @ (np.asarray(point, dtype=np.float64) - c1))
    return (point - was) / dt


class WoundMotion:
    """Tracks a wound's frames, one per control step (:meth:`update`), and estimates its motion.

    Attributes:
        speed: the wound centre's speed over the last step (m/s), 0 before two frames.
        acceleration: the change of that velocity over the last step, per second (m/s^2), 0 before three.
    """

    def __init__(self):
        self.reset()

    def reset(self) -> None:
        """Forget the frames (a new throw, or a gap in the registrations)."""
        self._previous: tuple | None = None
        self._current: tuple | None = None
        self._centre_velocity: np.ndarray | None = None
        self._dt = 0.0
        self.speed = 0.0
        self.acceleration = 0.0

    def update(self, frame: tuple, dt: float) -> None:
        """Add the wound's frame (centre (3,) m, rotation (3, 3)) registered ``dt`` s after the last."""
        if self._current is not None:
            velocity = (frame[0] - self._current[0]) / dt
            if self._centre_velocity is not None:
                self.acceleration = float(np.linalg.norm(velocity - self._centre_velocity)) / dt
            self._centre_velocity = velocity
            self.speed = float(np.linalg.norm(velocity))
        self._previous, self._current, self._dt = self._current, frame, dt

    def point_velocity(self, point: np.ndarray) -> np.ndarray:
        """Velocity (3,) m/s of the wound's material point at ``point`` over the last step; zeros before two
        frames."""
        if self._previous is None:
            return np.zeros(3)
        return point_velocity(self._previous, self._current, point, self._dt)
