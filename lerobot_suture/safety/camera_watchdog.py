"""A stale-camera watchdog: flags an endoscope whose frames stop changing while the arm moves.

A frozen or dropping endoscope still delivers a plausible picture, one the policy has seen, so an
image-space out-of-distribution score can miss it: the frame itself is in distribution, only out of date.
Its signature is in time instead: the measured pose moves while the frame stays byte-identical, or no frame
comes at all.

Per control step (0.1 s) ``CameraWatchdog.update`` takes the frame and the measured pose
``[x, y, z, r11, r21, r31, r12, r22, r32, jaw]`` (position in m, then the first two columns of the rotation
matrix). A step is *stale* when the frame is missing or empty, or when it equals the previous frame byte for
byte while the arm moved since that frame by at least ``min_motion`` (m) in position or ``min_rotation``
(rad) in orientation. A step where the arm did not move cannot tell a live camera from a frozen one, so it
neither counts as stale nor ends a run of stale steps; a step where the arm moved and the frame changed ends
it. ``patience`` stale steps in a row flag the camera until ``reset``. Pure numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lerobot_suture.sim.geometry import matrix_from_rot6, rotation_angle_of


@dataclass
class CameraWatchdogConfig:
    """Thresholds of the stale-camera watchdog.

    Args:
        min_motion: jaw-tip position change since the previous frame that counts as moving (m), > 0.
        min_rotation: jaw orientation change since the previous frame that counts as moving (rad), > 0.
        patience: stale steps in a row that flag the camera, >= 1.
    """

    min_motion: float = 0.001
    min_rotation: float = 0.035
    patience: int = 2

    def __post_init__(self):
        if not self.min_motion > 0:
            raise ValueError(f"`min_motion` must be in (0, inf) m. Got {self.min_motion}.")
        if not self.min_rotation > 0:
            raise ValueError(f"`min_rotation` must be in (0, inf) rad. Got {self.min_rotation}.")
        if self.patience < 1:
            raise ValueError(f"`patience` must be >= 1. Got {self.patience}.")


def rotation_angle(rot6_a: np.ndarray, rot6_b: np.ndarray) -> float:
    """Angle (rad, in [0, pi]) between the rotations of two pairs of columns, (6,) each; nan if degenerate."""
    try:
        relative = matrix_from_rot6(rot6_a).T @ matrix_from_rot6(rot6_b)
    except ValueError:
        return math.nan
    return rotation_angle_of(relative)


class CameraWatchdog:
    """Flags a stale endoscope from its frames and the arm's measured pose, one control step at a time.

    Attributes:
        stale_steps: the current run of stale steps.
        flagged_at: the step index (0-based, since ``reset``) at which the camera was flagged; None if not.
    """

    def __init__(self, config: CameraWatchdogConfig | None = None):
        self.config = config or CameraWatchdogConfig()
        self.reset()

    def reset(self) -> None:
        """Start over: no previous frame, no stale steps, not flagged."""
        self.step = 0
        self.stale_steps = 0
        self.flagged_at: int | None = None
        self._frame: np.ndarray | None = None
        self._pose: np.ndarray | None = None

    @property
    def flagged(self) -> bool:
        return self.flagged_at is not None

    def update(self, frame: np.ndarray | None, pose: np.ndarray) -> bool:
        """Take this step's frame and measured pose; returns whether the camera is flagged stale.

        Args:
            frame: (H, W, 3) uint8 image, or None when the camera delivered nothing.
            pose: (10,) measured pose (m, rotation columns, jaw closure).
        """
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (10,):
            raise ValueError(f"`pose` must have shape (10,). Got {pose.shape}.")
        stale = self._stale(frame, pose)
        if stale is True:
            self.stale_steps += 1
        elif stale is False:
            self.stale_steps = 0
        if self.flagged_at is None and self.stale_steps >= self.config.patience:
            self.flagged_at = self.step
        self.step += 1
        return self.flagged

    def _stale(self, frame: np.ndarray | None, pose: np.ndarray) -> bool | None:
        """True (stale), False (live) or None (cannot tell); keeps the last frame and its pose."""
        if frame is None or np.size(frame) == 0:
            return True
        frame = np.asarray(frame)
        previous, previous_pose = self._frame, self._pose
        # Copied: a caller may reuse its buffer, which would make every frame equal its predecessor.
        self._frame, self._pose = frame.copy(), pose
        if previous is None or not self._moved(previous_pose, pose):
            return None
        return bool(np.array_equal(frame, previous))

    def _moved(self, before: np.ndarray, after: np.ndarray) -> bool:
        if float(np.linalg.norm(after[:3] - before[:3])) >= self.config.min_motion:
            return True
        # A degenerate orientation (nan) cannot show motion; the position alone decides.
        return rotation_angle(before[3:9], after[3:9]) >= self.config.min_rotation
