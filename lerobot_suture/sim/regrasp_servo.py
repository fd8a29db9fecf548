"""A scripted regrasp on what the robot measures: the chain's opt-in alternative to a learned one
(``lerobot-suture chain --scripted_regrasp=true``).

A learned extract policy places the regrasp half a millimetre across the jaw's faces from the grasp and closes
there (``studies/benchmarks/extraction_failures.py``), where the wire must lie between the faces. Once it holds
the tip, it pulls the needle out in nearly every extraction episode. The planned regrasp is itself an observation
(``regrasp_target``, :mod:`lerobot_suture.sim.regrasp_target`): the motion from the jaw's measured pose to the
grasp, planned from the registered marks or from where the jaw let go. A servo on it needs only what a real
system has: the arm's kinematics, the registration and the jaw's encoder.

:class:`RegraspServo` runs the scripted expert's regrasp phases (``expert_plans.extraction``) on those
measurements alone:

1. ``release``: open the jaw where it is;
2. ``back_off``: draw it :data:`~lerobot_suture.sim.extraction.BACK_OFF` back along its axis;
3. ``reach``: to that distance short of the grasp, turning about the jaw's axis against the pull's sense
   (:func:`~lerobot_suture.sim.extraction.reach_step`), then ``advance`` onto the grasp;
4. ``settle``: hold the open jaw there ``settle_steps`` control steps; ``close``: close it, and wait for the
   encoder to stop.

A jaw that stops short of closed holds the wire (0.80-0.88 of its travel, ``sim.subtasks``): the regrasp is
done (``held``). One that closes fully closed on nothing: it opens, backs off and reaches again, up to
``attempts`` closings, each ``search_depth`` further along the jaw's axis than the last. The plan puts the wire at
the jaw's tip, the outer edge of where closing faces catch it (``sim.needle_capture``: up to 6 mm inside the jaw,
a wire radius beyond its tip), so a plan that lies short of the wire misses by a fraction of a millimetre along
that axis, and a deeper closing can catch it (the running suture's throws: ``docs/results.md``). The needle's
pose and the simulator's contact flags are never read.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lerobot_suture.checks import check_count, check_jaw_thresholds, check_positive
from lerobot_suture.sim.extraction import BACK_OFF, reach_step, turn_left
from lerobot_suture.sim.geometry import matrix_from_rot6, pose_vector, step_towards
from lerobot_suture.sim.needle_capture import JAW_GRIP_LENGTH
from lerobot_suture.sim.relative_actions import measured_jaw
from lerobot_suture.sim.subtasks import JAW_INDEX, STOPPED_CHANGE
from lerobot_suture.sim.task import (
    ANGLE_TOLERANCE,
    APPROACH_SPEED,
    CONTROL_DT,
    DESCEND_SPEED,
    POSITION_TOLERANCE,
    TURN_RATE,
)

_CLOSE_STEPS = 10
"""Control steps a closing jaw is given to stop before it is judged where it is."""


@dataclass(frozen=True)
class RegraspServoConfig:
    """Args:
    approach_speed: jaw speed on the back-off and the reach (m/s), > 0; the expert's.
    descend_speed: jaw speed on the advance onto the grasp (m/s), > 0; the expert's.
    turn_rate: largest turn of the jaw (rad/s), > 0; the expert's.
    position_tolerance: distance to a waypoint that counts as reached (m), > 0; the expert's.
    angle_tolerance: turn left to a waypoint's heading that counts as reached (rad), > 0; the expert's.
    settle_steps: control steps the open jaw holds the grasp before it closes, >= 0.
    closed_above: jaw closure above which a closing counts as closed, in (0, 1) (the chain's rules').
    holding_below: closure below which a closed jaw holds the wire, in (closed_above, 1].
    attempts: closings before the servo hands over whatever it holds, >= 1.
    search_depth: how much further along the jaw's axis each closing after a miss aims than the one before (m),
        in [0, 0.002]: the wire then sits that much deeper between the faces.
    control_dt: the control period (s), > 0.
    """

    approach_speed: float = APPROACH_SPEED
    descend_speed: float = DESCEND_SPEED
    turn_rate: float = TURN_RATE
    position_tolerance: float = POSITION_TOLERANCE
    angle_tolerance: float = ANGLE_TOLERANCE
    settle_steps: int = 3
    closed_above: float = 0.5
    holding_below: float = 0.95
    attempts: int = 5
    search_depth: float = 0.001
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
                "control_dt",
            ),
        )
        check_count(self, "settle_steps", 0)
        check_count(self, "attempts", 1)
        if not 0.0 <= self.search_depth <= 0.002:
            raise ValueError(f"`search_depth` must be in [0, 0.002] m. Got {self.search_depth!r}.")
        if (self.attempts - 1) * self.search_depth > JAW_GRIP_LENGTH - 0.001:
            raise ValueError(
                f"The last closing would aim {(self.attempts - 1) * self.search_depth * 1e3:.1f} mm inside the jaw, "
                f"past its {JAW_GRIP_LENGTH * 1e3:.0f} mm faces less a millimetre: lower `attempts` or `search_depth`."
            )
        check_jaw_thresholds(self.closed_above, self.holding_below)


def closing_verdict(
    closure: float, last_closure: float | None, steps: int, closed_above: float, holding_below: float
) -> str | None:
    """How a closing stands at its ``steps``-th step (0 the first after the command), the jaw reading ``closure``
    now and ``last_closure`` a step before (None: none yet): None while it still moves and has steps left
    (:data:`_CLOSE_STEPS`), else ``"held"`` where it stopped short of closed (between ``closed_above`` and
    ``holding_below``: the wire stops it), ``"empty"`` where not."""
    stopped = last_closure is not None and abs(closure - last_closure) < STOPPED_CHANGE
    if not (closure > closed_above and stopped) and steps < _CLOSE_STEPS:
        return None
    return "held" if closed_above < closure < holding_below else "empty"


def grasp_from_target(agent_pos: np.ndarray, regrasp_target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The planned grasp in the arm's frame (position (3,) m, rotation (3, 3)) that ``regrasp_target`` (9,), the
    motion from the measured pose ``agent_pos`` (10,) in the jaw frame, names."""
    jaw_pos, jaw_rot = measured_jaw(agent_pos)
    target = np.asarray(regrasp_target, dtype=np.float64)
    return jaw_pos + jaw_rot @ target[:3], jaw_rot @ matrix_from_rot6(target[3:9])


class RegraspServo:
    """One regrasp (module docstring); :meth:`act` gives each control step's absolute target (10,) float32.

    Args:
        config: speeds, tolerances and thresholds.
    """

    def __init__(self, config: RegraspServoConfig | None = None):
        self.config = config or RegraspServoConfig()
        self.phase = "release"
        self.closings = 0
        self._misses = 0  # closings judged empty
        self._goal: np.ndarray | None = None
        self._settled = 0
        self._closing_steps = 0
        self._last_closure: float | None = None
        self.held = False
        """Whether the regrasp ended with the jaw on the wire (its encoder stopped short of closed)."""

    @property
    def done(self) -> bool:
        """Whether the jaw holds the wire, or the last allowed closing is over."""
        return self.phase == "done"

    def act(self, agent_pos: np.ndarray, regrasp_target: np.ndarray) -> np.ndarray:
        """The target for this step from the measured pose ``agent_pos`` (10,) and the planned regrasp
        ``regrasp_target`` (9,) of the same observation.

        Raises:
            RuntimeError: called after the regrasp is done.
        """
        if self.done:
            raise RuntimeError("The regrasp is done: hand the arm to the extract policy.")
        cfg = self.config
        pose = np.asarray(agent_pos, dtype=np.float64)
        jaw_pos, jaw_rot = measured_jaw(pose)
        grasp_pos, grasp_rot = grasp_from_target(pose, regrasp_target)
        grasp_pos = grasp_pos + self._misses * cfg.search_depth * grasp_rot[:, 2]  # deeper after each miss
        if self.phase == "close":
            target = self._close(float(pose[JAW_INDEX]), grasp_pos, grasp_rot)
            if target is not None:
                return target
        if self.phase == "release":
            self.phase = "back_off"
            return pose_vector(jaw_pos, jaw_rot, 0.0).astype(np.float32)
        if self.phase == "back_off":
            if self._goal is None:
                self._goal = jaw_pos - BACK_OFF * jaw_rot[:, 2]
            if np.linalg.norm(self._goal - jaw_pos) >= cfg.position_tolerance:
                step = step_towards(
                    jaw_pos, jaw_rot, self._goal, jaw_rot, cfg.approach_speed * cfg.control_dt, 0.0
                )
                return pose_vector(*step, 0.0).astype(np.float32)
            self.phase, self._goal = "reach", None
        max_turn = cfg.turn_rate * cfg.control_dt
        if self.phase == "reach":
            short = grasp_pos - BACK_OFF * grasp_rot[:, 2]
            left = turn_left(jaw_rot, grasp_rot)
            if np.linalg.norm(short - jaw_pos) >= cfg.position_tolerance or left >= cfg.angle_tolerance:
                step = reach_step(
                    jaw_pos, jaw_rot, short, grasp_rot, left, cfg.approach_speed * cfg.control_dt, max_turn
                )
                return pose_vector(*step, 0.0).astype(np.float32)
            self.phase = "advance"
        if self.phase == "advance":
            if np.linalg.norm(grasp_pos - jaw_pos) >= cfg.position_tolerance:
                step = step_towards(
                    jaw_pos, jaw_rot, grasp_pos, grasp_rot, cfg.descend_speed * cfg.control_dt, max_turn
                )
                return pose_vector(*step, 0.0).astype(np.float32)
            self.phase = "settle"
        if self._settled < cfg.settle_steps:
            self._settled += 1
            return pose_vector(grasp_pos, grasp_rot, 0.0).astype(np.float32)
        self.phase, self._settled, self._closing_steps = "close", 0, 0
        self._last_closure = None
        self.closings += 1
        return pose_vector(grasp_pos, grasp_rot, 1.0).astype(np.float32)

    def _close(self, closure: float, grasp_pos: np.ndarray, grasp_rot: np.ndarray) -> np.ndarray | None:
        """The closing step's target, or None when the closing is judged and the servo moved on (``done``, or a
        back-off for another reach)."""
        cfg = self.config
        verdict = closing_verdict(
            closure, self._last_closure, self._closing_steps, cfg.closed_above, cfg.holding_below
        )
        self._last_closure, self._closing_steps = closure, self._closing_steps + 1
        if verdict is None:
            return pose_vector(grasp_pos, grasp_rot, 1.0).astype(np.float32)
        self.held = verdict == "held"
        if self.held or self.closings >= cfg.attempts:
            self.phase = "done"
            return pose_vector(grasp_pos, grasp_rot, 1.0).astype(np.float32)
        self.phase, self._misses = (
            "release",
            self._misses + 1,
        )  # closed on nothing: open, back off, reach again
        return None
