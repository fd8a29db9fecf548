"""A scripted pick-up on what the robot measures: the chain's opt-in alternative to a learned one
(``lerobot-suture chain --scripted_pick_up=true``).

Between two throws of the running suture the arm lays the needle down on the phantom and picks it up again at its
tail. A learned pick-up has to find the needle in the images, and on the phantom it closes beside it
(``docs/results.md``). The needle lies where the jaw let go of it, and the robot measured that jaw:

- a jaw closed on the wire seats it straight across its faces (``sim.needle_capture``), so with the grasp model of
  ``geometry.grasp_transform`` the jaw's measured pose at the last step it held the needle gives the needle's pose,
  once the arc angle it held it at is known: the extract's regrasp takes it :data:`~sim.extraction.REGRASP_ANGLE`
  from the tip, an insert holds it at ``task.GRASP_ANGLE``;
- the needle then drops onto the tissue: :func:`resting_needle` lays that pose flat on the registered surface (the
  height of the current throw's marks; the phantom only glides and turns about the vertical, so the surface is
  level), its plane's normal into the tissue, its wire a radius above it;
- what lies on the phantom moves with it: the plan follows the registered marks from the step the pick-up began
  (:func:`carried_by_phantom`), as a registration that tracks the phantom reports them.

:class:`PickupServo` runs the scripted expert's pick-up (``expert_plans.pickup``) on that estimate: ``reach`` the
open jaw to ``approach_height`` above the grasp an insertion starts from (``task.GRASP_ANGLE``), turned into it;
``lower`` onto it, ``settle``, ``close``, and wait for the encoder to stop. A jaw that stops short of closed holds
the wire (``sim.subtasks``): done, and the next throw's insert acts. One that closes fully closed on nothing: it
opens, rises, and tries again beside the last aim, across the jaw's faces, where the estimate's error lies
(:func:`search_offset`), up to ``attempts`` closings. The needle's pose and the simulator's contact flags are never
read.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lerobot_suture.checks import check_count, check_jaw_thresholds, check_positive
from lerobot_suture.sim.extraction import REGRASP_ANGLE
from lerobot_suture.sim.geometry import (
    cross3,
    grasp_transform,
    jaw_holding,
    needle_in_world,
    pose_vector,
    rotvec_from_matrix,
    step_towards,
)
from lerobot_suture.sim.needle_capture import CAPTURE_HALF_GAP
from lerobot_suture.sim.regrasp_servo import closing_verdict
from lerobot_suture.sim.relative_actions import measured_jaw
from lerobot_suture.sim.subtasks import JAW_INDEX
from lerobot_suture.sim.task import (
    ANGLE_TOLERANCE,
    APPROACH_SPEED,
    CONTROL_DT,
    DESCEND_SPEED,
    GRASP_ANGLE,
    POSITION_TOLERANCE,
    TURN_RATE,
)

WIRE_RADIUS = 0.0004
"""The needle wire's radius (m): the scene's needle geometry, a catalogue number on a real system."""
SURFACE_NORMAL = np.array([0.0, 0.0, 1.0])
"""The tissue surface's normal, out of the tissue: the phantom glides and turns about the vertical only."""


@dataclass(frozen=True)
class PickupServoConfig:
    """Args:
    approach_speed: jaw speed on the reach (m/s), > 0; the expert's.
    descend_speed: jaw speed lowering onto the grasp (m/s), > 0; the expert's.
    turn_rate: largest turn of the jaw (rad/s), > 0; the expert's.
    position_tolerance: distance to a waypoint that counts as reached (m), > 0; the expert's.
    angle_tolerance: turn to a waypoint's orientation that counts as reached (rad), > 0; the expert's.
    approach_height: height above the grasp the open jaw reaches before it lowers (m), > 0; the expert's.
    settle_steps: control steps the open jaw holds the grasp before it closes, >= 0.
    closed_above: jaw closure above which a closing counts as closed, in (0, 1) (the chain's rules').
    holding_below: closure below which a closed jaw holds the wire, in (closed_above, 1].
    attempts: closings before the servo hands over whatever it holds, >= 1.
    search_step: how far across the jaw's faces each closing after a miss aims beside the ones before (m), in
        (0, 2 * CAPTURE_HALF_GAP]: the faces catch a wire within ``CAPTURE_HALF_GAP`` of their mid-plane, so
        steps up to twice that leave no gap between the closings.
    control_dt: the control period (s), > 0.
    """

    approach_speed: float = APPROACH_SPEED
    descend_speed: float = DESCEND_SPEED
    turn_rate: float = TURN_RATE
    position_tolerance: float = POSITION_TOLERANCE
    angle_tolerance: float = ANGLE_TOLERANCE
    approach_height: float = 0.012
    settle_steps: int = 2
    closed_above: float = 0.5
    holding_below: float = 0.95
    attempts: int = 5
    search_step: float = 0.0015
    control_dt: float = CONTROL_DT

    def __post_init__(self):
        check_positive(
            self,
            (
                "approach_speed",
                "descend_speed",
                "turn_rate",
                "position_tolerance",
                "angle_tolerance",
                "approach_height",
                "control_dt",
            ),
        )
        check_count(self, "settle_steps", 0)
        check_count(self, "attempts", 1)
        if not 0.0 < self.search_step <= 2.0 * CAPTURE_HALF_GAP:
            raise ValueError(
                f"`search_step` must be in (0, {2.0 * CAPTURE_HALF_GAP}] m: the faces catch a wire within "
                f"{CAPTURE_HALF_GAP * 1e3:.0f} mm of their mid-plane. Got {self.search_step!r}."
            )
        check_jaw_thresholds(self.closed_above, self.holding_below)


def resting_needle(
    release_pos: np.ndarray,
    release_rot: np.ndarray,
    held_angle: float,
    surface_height: float,
    wire_radius: float = WIRE_RADIUS,
) -> tuple[np.ndarray, np.ndarray]:
    """Where a needle lies once a jaw at ``release_pos`` (3,) m, ``release_rot`` (3, 3) that held it at arc angle
    ``held_angle`` (rad) let go of it above a level surface at height ``surface_height`` (m): the held needle's pose
    (the nominal grasp of ``geometry.grasp_transform`` at that angle), turned flat about its centre with its
    plane's normal into the tissue, its centre lowered or raised so the wire's axis lies ``wire_radius`` (m) above
    the surface. Returns (centre (3,) m, rotation (3, 3)), world."""
    centre, rotation = needle_in_world(release_pos, release_rot, *grasp_transform(held_angle, 0.0, 0.0))
    normal = -SURFACE_NORMAL
    x_axis = rotation[:, 0] - (rotation[:, 0] @ normal) * normal
    x_axis /= np.linalg.norm(x_axis)
    flat = np.column_stack([x_axis, cross3(normal, x_axis), normal])
    centre = centre + (surface_height + wire_radius - centre @ SURFACE_NORMAL) * SURFACE_NORMAL
    return centre, flat


def marks_frame(marks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The frame the registered marks (6,) m (the current throw's entry, then exit point) give the phantom: origin
    (3,) m between them, rotation (3, 3) with x from entry to exit across the level surface and z its normal."""
    entry, exit_ = np.asarray(marks[:3], dtype=np.float64), np.asarray(marks[3:6], dtype=np.float64)
    across = exit_ - entry
    across = across - (across @ SURFACE_NORMAL) * SURFACE_NORMAL
    x_axis = across / np.linalg.norm(across)
    return 0.5 * (entry + exit_), np.column_stack([x_axis, cross3(SURFACE_NORMAL, x_axis), SURFACE_NORMAL])


def carried_by_phantom(
    pose: tuple[np.ndarray, np.ndarray], marks_then: np.ndarray, marks_now: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A pose (position (3,) m, rotation (3, 3)) resting on the phantom when the marks read ``marks_then`` (6,),
    where the phantom has carried it once they read ``marks_now`` (6,): the phantom glides and turns, and what lies
    on it moves with it."""
    origin_then, frame_then = marks_frame(marks_then)
    origin_now, frame_now = marks_frame(marks_now)
    turn = frame_now @ frame_then.T
    return origin_now + turn @ (pose[0] - origin_then), turn @ pose[1]


def search_offset(miss: int, step: float) -> float:
    """How far across the jaw's faces (m, along the jaw's y axis) the closing after ``miss`` misses aims from the
    planned grasp: 0, then ``step``, ``-step``, ``2 step``, ``-2 step``, ..."""
    if miss == 0:
        return 0.0
    ring = (miss + 1) // 2
    return step * ring * (1.0 if miss % 2 else -1.0)


class PickupServo:
    """One pick-up of a needle that lies at ``needle`` (module docstring); :meth:`act` gives each control step's
    absolute target (10,) float32.

    Args:
        needle: (centre (3,) m, rotation (3, 3)), world, where the needle lies: :func:`resting_needle`.
        marks: (6,) m, the registered marks when the needle lay there: a phantom that moves since carries the
            needle, and the plan follows the marks (:func:`carried_by_phantom`).
        config: speeds, tolerances and thresholds.
    """

    def __init__(
        self,
        needle: tuple[np.ndarray, np.ndarray],
        marks: np.ndarray,
        config: PickupServoConfig | None = None,
    ):
        self.config = config or PickupServoConfig()
        self._planned = jaw_holding(*needle, *grasp_transform(GRASP_ANGLE, 0.0, 0.0))
        self._marks = np.asarray(marks, dtype=np.float64).copy()
        self.grasp = self._planned
        """The planned grasp: the jaw pose (position (3,) m, rotation (3, 3)) an insertion starts from, where the
        marks last read put it."""
        self.phase = "reach"
        self.closings = 0
        self._misses = 0
        self._settled = 0
        self._closing_steps = 0
        self._last_closure: float | None = None
        self.held = False
        """Whether the pick-up ended with the jaw on the wire (its encoder stopped short of closed)."""

    @property
    def done(self) -> bool:
        """Whether the jaw holds the wire, or the last allowed closing is over."""
        return self.phase == "done"

    def _aim(self) -> tuple[np.ndarray, np.ndarray]:
        """The grasp this closing aims at: the planned one, beside it across the faces after a miss."""
        position, rotation = self.grasp
        offset = search_offset(self._misses, self.config.search_step)
        return position + offset * rotation[:, 1], rotation

    def act(self, agent_pos: np.ndarray, marks: np.ndarray) -> np.ndarray:
        """The target for this step from the measured pose ``agent_pos`` (10,) and the registered marks ``marks``
        (6,) m of the same observation.

        Raises:
            RuntimeError: called after the pick-up is done.
        """
        if self.done:
            raise RuntimeError("The pick-up is done: hand the arm to the insert policy.")
        cfg = self.config
        pose = np.asarray(agent_pos, dtype=np.float64)
        jaw_pos, jaw_rot = measured_jaw(pose)
        self.grasp = carried_by_phantom(self._planned, self._marks, marks)
        grasp_pos, grasp_rot = self._aim()
        max_turn, dt = cfg.turn_rate * cfg.control_dt, cfg.control_dt
        if self.phase == "close":
            verdict = closing_verdict(
                float(pose[JAW_INDEX]),
                self._last_closure,
                self._closing_steps,
                cfg.closed_above,
                cfg.holding_below,
            )
            self._last_closure, self._closing_steps = float(pose[JAW_INDEX]), self._closing_steps + 1
            if verdict is None:
                return pose_vector(grasp_pos, grasp_rot, 1.0).astype(np.float32)
            self.held = verdict == "held"
            if self.held or self.closings >= cfg.attempts:
                self.phase = "done"
                return pose_vector(grasp_pos, grasp_rot, 1.0).astype(np.float32)
            # Closed on nothing: open where it is, and reach again beside the last aim.
            self.phase, self._misses = "reach", self._misses + 1
            return pose_vector(jaw_pos, jaw_rot, 0.0).astype(np.float32)
        above = grasp_pos + cfg.approach_height * SURFACE_NORMAL
        if self.phase == "reach":
            turn = float(np.linalg.norm(rotvec_from_matrix(jaw_rot.T @ grasp_rot)))
            if np.linalg.norm(above - jaw_pos) >= cfg.position_tolerance or turn >= cfg.angle_tolerance:
                step = step_towards(jaw_pos, jaw_rot, above, grasp_rot, cfg.approach_speed * dt, max_turn)
                return pose_vector(*step, 0.0).astype(np.float32)
            self.phase = "lower"
        if self.phase == "lower":
            if np.linalg.norm(grasp_pos - jaw_pos) >= cfg.position_tolerance:
                step = step_towards(jaw_pos, jaw_rot, grasp_pos, grasp_rot, cfg.descend_speed * dt, max_turn)
                return pose_vector(*step, 0.0).astype(np.float32)
            self.phase = "settle"
        if self._settled < cfg.settle_steps:
            self._settled += 1
            return pose_vector(grasp_pos, grasp_rot, 0.0).astype(np.float32)
        self.phase, self._settled, self._closing_steps, self._last_closure = "close", 0, 0, None
        self.closings += 1
        return pose_vector(grasp_pos, grasp_rot, 1.0).astype(np.float32)


class NeedleRelease:
    """Where the jaw last held the needle, from the measured pose at each control step and the high level's reading
    of the subtask: the pose a :class:`PickupServo` plans from (:func:`resting_needle`).

    Args:
        closed_above: jaw closure above which the jaw counts as closed, in (0, 1).
        holding_below: closure below which a closed jaw holds the wire.
    """

    def __init__(self, closed_above: float = 0.5, holding_below: float = 0.95):
        self.closed_above, self.holding_below = closed_above, holding_below
        self.pose: tuple[np.ndarray, np.ndarray] | None = None
        """The jaw's measured pose (position (3,) m, rotation (3, 3)) at the last step it held the needle."""
        self.held_angle = GRASP_ANGLE
        """The arc angle (rad) it held the needle at: an insert's grasp, or the extract's regrasp near the tip."""

    def update(self, agent_pos: np.ndarray, subtask: str) -> None:
        """Read one step's measured pose ``agent_pos`` (10,) in ``subtask`` (``sim.subtasks.SUBTASKS``)."""
        if self.closed_above < float(agent_pos[JAW_INDEX]) < self.holding_below:
            self.pose = measured_jaw(agent_pos)
            self.held_angle = GRASP_ANGLE if subtask in ("insert", "pick_up") else REGRASP_ANGLE
