"""A scripted pull on what the robot measures: the chain's opt-in alternative to a learned one
(``lerobot-suture chain --scripted_regrasp=true --scripted_pull=true``).

Once the jaw holds the needle near its tip, the extraction is a turn of the needle about its own centre: every
point of the wire then follows the arc the tip cut, and the tail leaves through the exit hole without moving the
tissue sideways (``sim.extraction``). A learned pull has to find that turn from images; on the running suture's
throws the pull trained on the recipe's extracts stalls in most of them, straining the tissue while it jitters
(``docs/results.md``).

The turn needs no sight of the needle. A jaw closed on the wire seats it straight across its faces
(``sim.needle_capture``), so the jaw's measured pose at the hold gives the needle's: with the grasp model of
``geometry.grasp_transform`` the needle's centre lies one radius along the jaw's y axis, and its plane's normal is
the jaw's z axis. :class:`PullServo` turns the jaw about that centre and axis at the scripted expert's drive rate,
through :data:`PULL_ANGLE`: the tail of a needle whose tip stands at least ``PROTRUSION_RANGE[0]`` of arc past the
exit point then ends ``PULL_MARGIN`` past it, as the expert's pull does. Turning further moves a needle already out
through the air. The needle's pose and the simulator's contact flags are never read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lerobot_suture.checks import check_positive
from lerobot_suture.sim.extraction import PROTRUSION_RANGE, PULL_MARGIN
from lerobot_suture.sim.geometry import NEEDLE_RADIUS, matrix_from_rotvec, pose_vector
from lerobot_suture.sim.relative_actions import measured_jaw
from lerobot_suture.sim.task import CONTROL_DT, DRIVE_RATE

PULL_ANGLE = math.pi - PROTRUSION_RANGE[0] + PULL_MARGIN
"""How far the pull turns the needle about its centre (rad): the tail of a needle protruding at least
``PROTRUSION_RANGE[0]`` past the exit point ends ``PULL_MARGIN`` past it."""


@dataclass(frozen=True)
class PullServoConfig:
    """Args:
    drive_rate: turning rate about the needle's centre (rad/s), > 0; the expert's.
    pull_angle: the whole turn (rad), in (0, pi]: a half turn brings the tail to where the tip was at the hold.
    control_dt: the control period (s), > 0.
    """

    drive_rate: float = DRIVE_RATE
    pull_angle: float = PULL_ANGLE
    control_dt: float = CONTROL_DT

    def __post_init__(self):
        check_positive(self, ("drive_rate", "control_dt"))
        if not 0.0 < self.pull_angle <= math.pi:  # NaN fails too
            raise ValueError(f"`pull_angle` must be in (0, pi] rad. Got {self.pull_angle!r}.")


def needle_axis_from_jaw(jaw_pos: np.ndarray, jaw_rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The centre (3,) m and plane normal (3,) of the needle a jaw at ``jaw_pos`` (3,) m, ``jaw_rot`` (3, 3) holds
    with the nominal grasp (``geometry.grasp_transform``: the centre one radius along the jaw's y axis)."""
    return jaw_pos + NEEDLE_RADIUS * jaw_rot[:, 1], jaw_rot[:, 2]


def turned_jaw(
    jaw_pos: np.ndarray, jaw_rot: np.ndarray, centre: np.ndarray, axis: np.ndarray, angle: float
) -> tuple[np.ndarray, np.ndarray]:
    """The jaw pose (position (3,) m, rotation (3, 3)) that the jaw at ``jaw_pos``, ``jaw_rot`` takes when the needle
    it holds turns ``angle`` (rad) about ``centre`` (3,) m in the pull's sense, about the plane normal ``axis`` (3,)
    (``geometry.InsertionFrame.needle_rotation``: a drive turns the needle by minus its angle about its z axis)."""
    turn = matrix_from_rotvec(-angle * np.asarray(axis, dtype=np.float64))
    return centre + turn @ (jaw_pos - centre), turn @ jaw_rot


class PullServo:
    """One pull from the jaw's measured pose when it took hold (module docstring); :meth:`act` gives each control
    step's absolute target (10,) float32, the jaw closed.

    Args:
        agent_pos: (10,) the measured pose at the first step of the pull (the jaw on the wire).
        config: rate and turn.
    """

    def __init__(self, agent_pos: np.ndarray, config: PullServoConfig | None = None):
        self.config = config or PullServoConfig()
        self._start = measured_jaw(np.asarray(agent_pos, dtype=np.float64))
        self.centre, self.axis = needle_axis_from_jaw(*self._start)
        self.angle = 0.0
        """How far the targets have turned the needle so far (rad)."""

    @property
    def done(self) -> bool:
        """Whether the last target of the turn has been given."""
        return self.angle >= self.config.pull_angle

    def act(self) -> np.ndarray:
        """The next target: the held pose turned one control step further, up to the whole turn.

        Raises:
            RuntimeError: called after the pull is done.
        """
        if self.done:
            raise RuntimeError("The pull is done: hand the arm to the next subtask's policy.")
        cfg = self.config
        self.angle = min(cfg.pull_angle, self.angle + cfg.drive_rate * cfg.control_dt)
        return pose_vector(*turned_jaw(*self._start, self.centre, self.axis, self.angle), 1.0).astype(
            np.float32
        )
