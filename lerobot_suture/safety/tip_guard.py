"""The CBF over one suture throw, from what a real system measures: one filter for the env and the robot path.

:class:`TipGuard` keeps the held needle's tip out of the tissue everywhere but the wound. Its safe set is the
union of two convex sets, each tightened by the margin ``m``:

- ``above``: the half-space above the tissue surface, ``height >= m`` (:mod:`~lerobot_suture.safety.surface_cbf`);
- ``wound``: the throw's ellipsoid, ``h >= h_m`` (:func:`~lerobot_suture.safety.cbf.filter_velocity_discrete`).

The tissue outside the ellipsoid is the one region the tip may not enter. The filter is on whenever the needle
is held and a wound is registered, whatever the throw's phase: an action can neither leave the tissue and come
back elsewhere, nor end the guard by loosening the jaw without letting go.

The union is not convex, so the filter works in one convex *mode* at a time (``above`` or ``wound``) and keeps
the tip's commanded end point, hence its straight commanded segment, inside that mode's tightened set. It
enters a mode only while the tip and every end point it commanded in the last ``latency_steps`` control steps
lie in that mode's set, choosing, among the modes it may be in, the one whose filtered velocity is nearest the
nominal one. Why this covers latency and an arm that falls short: an arm that moves the tip in straight lines
towards commanded end points keeps it in the convex hull of where it was and of those end points. Within a mode
that hull is inside the mode's set; at a switch the tip and every end point still in flight already lie in the
new mode's set, and so does every end point after. The margin covers the tip's distance from that path
(tracking error plus grasp-model error). A tip found in a margin band, in neither tightened set, is brought
back into the ellipsoid if it is inside it, else lifted (each mode's barrier never decreases over the step),
and the robot path lets the jaw turn no further meanwhile, so that no sweep of the tip's lever arm works
against the recovery. On tissue that moves, the filter works on the tip's
motion relative to the wound's measured motion (:mod:`~lerobot_suture.safety.wound_motion`).

It is used two ways, with the same rules and the same filter:

- :meth:`TipGuard.filter_target` (the robot path, ``suture_cbf`` processor step): from the measured pose of
  the needle holder, the commanded target pose, a :class:`GraspModel` (where the needle sits in the jaw) and a
  registered :class:`Wound` (entry and exit points, tissue normal). The needle tip and the commanded tip
  motion come from kinematics; whether the needle may be held comes from the measured jaw closure and the
  commanded one. It returns the target pose moved so that the tip's commanded end point is
  ``tip + v_safe * control_dt``. Nothing is read from a simulator.
- :meth:`TipGuard.filter_velocity` (the env path, ``CBFActionWrapper``): the env hands over the tip and its
  nominal velocity at the moment its controller computes them, and whether the needle is held.

The throw's *phase* (idle, active, done) is reported, not what switches the filter: it becomes active when the
needle is held in a grasp a throw starts from with its tip in the tightened ellipsoid, and done when the needle
is released. Units: m, s, rad.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from lerobot_suture.safety.cbf import ellipsoid_h, margin_level
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.safety.surface_cbf import filter_velocity_surface, surface_height
from lerobot_suture.safety.wound import GraspModel, Wound, finite_vector
from lerobot_suture.safety.wound_motion import WoundMotion
from lerobot_suture.sim.geometry import (
    matrix_from_rot6,
    matrix_from_rotvec,
    rotvec_from_matrix,
    segment_distance,
)

PHASE_IDLE = "idle"
"""The throw has not begun."""
PHASE_ACTIVE = "active"
"""The throw has begun (the needle held in a throw grasp entered the tightened ellipsoid)."""
PHASE_DONE = "done"
"""The throw's needle was released after the throw began (a regrasped needle is guarded all the same)."""
MODE_ABOVE = "above"
"""The tip is kept above the tissue surface, by the margin."""
MODE_WOUND = "wound"
"""The tip is kept in the throw's ellipsoid, tightened by the margin."""

logger = logging.getLogger(__name__)
# Finite differences of an exact registration stay within the true bounds; these absorb rounding only.
_SPEED_TOLERANCE = 1e-6  # m/s
_ACCELERATION_TOLERANCE = 1e-4  # m/s^2

TRACKING_WINDOW = 30
"""Control steps over which the robot path's measured tracking error is the largest deviation."""
FIRM_HOLD = 0.8
"""A jaw reading (and command) at or above this holds the needle firmly: closed on the wire, it reads about 0.88."""
STILL_JAW = 0.02
"""A jaw whose reading changed less than this over a step is still (one closing on nothing is not)."""
MARGIN_CAP = 0.9
"""The tightening never exceeds this share of the smallest semi-axis (the tightened set stays non-empty)."""


class GuardResult(NamedTuple):
    """What the guard did with one control step's motion.

    Attributes:
        active: the throw's phase is ``active`` (the throw has begun and the needle is held).
        guarding: the needle may be held and a wound is registered: the filter was applied (or, disabled, would
            have been).
        v_nominal: (3,) m/s commanded tip velocity.
        v_safe: (3,) m/s tip velocity let through.
        intervened: ``v_safe`` differs from ``v_nominal``, or the command was replaced (a target without
            rotation, or one the arm would clip to its workspace).
        h: the ellipsoid's barrier at the tip (>= 0 inside it), NaN without a wound.
        filter_time: wall time of the filter call (s), NaN when it did not run.
        mode: ``above`` or ``wound``, the convex set the step was kept in ("" when not guarding).
        motion_exceeded: the wound moved faster, or accelerated harder, than the declared bounds
            (``CBFConfig.tissue_speed_max``, ``tissue_acceleration_max``): outside the filter's premises.
    """

    active: bool
    guarding: bool
    v_nominal: np.ndarray
    v_safe: np.ndarray
    intervened: bool
    h: float
    filter_time: float
    mode: str
    motion_exceeded: bool


@dataclass
class TipGuard:
    """The CBF on the held needle's tip, and the phase of the throw (see the module docstring).

    A new ``throw_index`` starts over; so does :meth:`reset`.

    Args:
        cbf: the filter's configuration (``enabled=False``: the phase and h are tracked, motions pass).
        held_jaw_range: measured jaw closures (0 open, 1 closed) at which the jaw may hold the needle: the arm
            lets go only below a command of 0.5, a jaw closed on the wire reads about 0.88 and one closed on
            nothing 1 (:meth:`filter_target` only). A jaw commanded to close (>= 0.5) may catch the needle
            whatever it reads, and counts as holding it too.
        latency_steps: control steps (>= 0) between a measurement and the motion of the command computed from
            it (observation plus command latency), as the arm declares it: how many commanded end points may
            still be in flight when the mode switches, and how long a jaw may have held the needle unseen.
        turn_sweep: how far (m, >= 0) a turn of the jaw may sweep the needle tip off its straight commanded
            segment on an arm that falls short of a commanded pose, rotation included (part of the margin;
            :meth:`filter_target` only). It caps the turn commanded per control step at ``max_turn``.
        max_tip_speed: the arm's largest tip speed (m/s, > 0), or None (unbounded). An arm that cannot go as
            fast as commanded falls short of the end point: harmless on still tissue, where the segment's points
            are in the set, but behind tissue that moves. Commands are slowed, relative to the tissue, so that
            the tip's speed stays within it.

    On the robot path the guard also measures how far the tip strays from the segment it was commanded
    (``tracking_error``, the largest deviation over the last ``TRACKING_WINDOW`` steps) and tightens the set by
    that much when it exceeds the configured margin: an arm that tracks worse than declared gets a wider margin.
    """

    cbf: CBFConfig = field(default_factory=lambda: CBFConfig(enabled=True))
    held_jaw_range: tuple[float, float] = (0.45, 0.97)
    latency_steps: int = 0
    turn_sweep: float = 0.0002
    max_tip_speed: float | None = None

    def __post_init__(self):
        low, high = self.held_jaw_range
        if not 0.0 <= low < high <= 1.0:
            raise ValueError(
                f"`held_jaw_range` must satisfy 0 <= low < high <= 1. Got {self.held_jaw_range}."
            )
        if isinstance(self.latency_steps, bool) or not isinstance(self.latency_steps, int):
            raise ValueError(f"`latency_steps` must be an integer >= 0. Got {self.latency_steps!r}.")
        if not 0 <= self.latency_steps <= 100:
            raise ValueError(f"`latency_steps` must be in [0, 100] control steps. Got {self.latency_steps}.")
        if isinstance(self.turn_sweep, bool) or not isinstance(self.turn_sweep, int | float):
            raise ValueError(f"`turn_sweep` must be a number >= 0 (m). Got {self.turn_sweep!r}.")
        if self.max_tip_speed is not None and not (
            isinstance(self.max_tip_speed, int | float) and 0.0 < self.max_tip_speed < math.inf
        ):
            raise ValueError(
                f"`max_tip_speed` must be a number > 0 (m/s) or None. Got {self.max_tip_speed!r}."
            )
        if not 0.0 <= self.turn_sweep < self.cbf.margin + 1e-12:
            raise ValueError(
                f"`turn_sweep` must be in [0, margin = {self.cbf.margin}] m (it is part of the margin). "
                f"Got {self.turn_sweep}."
            )
        self.reset()

    def reset(self) -> None:
        """Forget the throw: back to ``idle``, no mode, nothing in flight."""
        self.phase = PHASE_IDLE
        self._throw_index: int | None = None
        self._mode: str | None = None
        # Per commanded end point still possibly in flight: whether it lies in each mode's tightened set.
        self._in_flight: deque[tuple[bool, bool]] = deque(maxlen=self.latency_steps)
        # Per recent control step: whether the jaw may have held the needle (robot path).
        self._jaw_window: deque[bool] = deque(maxlen=self.latency_steps + 1)
        self._motion = WoundMotion()
        # The robot path's tracking measurement: commanded tip end points (the oldest is the one executing as
        # the next measurement is taken), the last measured tip, and the recent deviations (m).
        self._ends: deque[np.ndarray] = deque(maxlen=self.latency_steps + 1)
        self._steady: deque[bool] = deque(maxlen=self.latency_steps + 2)
        self._last_tip: np.ndarray | None = None
        self._last_grasp: GraspModel | None = None
        self._last_closure: float | None = None
        self._deviations: deque[float] = deque(maxlen=TRACKING_WINDOW)

    @property
    def tracking_error(self) -> float:
        """The largest deviation (m) of the measured tip from its commanded segment over the last
        ``TRACKING_WINDOW`` control steps (robot path; 0 before any)."""
        return max(self._deviations, default=0.0)

    def max_turn(self, grasp: GraspModel) -> float:
        """The largest turn (rad) of the jaw per control step: its sweep of the needle tip, at most
        ``1.25 r theta^2 / 8`` for a lever ``r`` (the jaw-to-tip distance) on an arm that interpolates towards
        the commanded rotation, stays within ``turn_sweep``; divided among the steps of declared latency."""
        lever = float(np.linalg.norm(grasp.tip_in_jaw()))
        return math.sqrt(8.0 * self.turn_sweep / (1.25 * lever)) / (self.latency_steps + 1)

    def margin(self, dt: float) -> float:
        """The tightening (m) for a control period ``dt`` s: the tracking margin (the configured one, or the
        measured ``tracking_error`` where larger), plus how far the tissue can stray within a step from where
        its measured velocity carries it (``tissue_acceleration_max dt^2``); 0 for the continuous-time filter.
        At most ``MARGIN_CAP`` of the smallest semi-axis."""
        if not self.cbf.discrete:
            return 0.0
        margin = max(self.cbf.margin, self.tracking_error) + self.cbf.tissue_acceleration_max * dt * dt
        return min(margin, MARGIN_CAP * float(np.min(self.cbf.semi_axes)))

    @property
    def mode(self) -> str | None:
        """``above`` or ``wound`` while guarding, else None."""
        return self._mode

    @property
    def throw_index(self) -> int | None:
        """The throw the phase is of (None before the first)."""
        return self._throw_index

    def observe(self, held: bool, throw_index: int | None = None) -> None:
        """After a step: a needle no longer held ends the throw's phase, and the wound's motion is measured
        afresh once it is held again (frames steps apart are no velocity); a new ``throw_index`` starts over."""
        if throw_index is not None and throw_index != self._throw_index:
            self.reset()
            self._throw_index = throw_index
        if not held:
            self._motion.reset()
            if self.phase == PHASE_ACTIVE:
                self.phase = PHASE_DONE

    def filter_velocity(
        self, tip: np.ndarray, v_nominal: np.ndarray, wound: Wound, held: bool, ready: bool, dt: float
    ) -> GuardResult:
        """One control step's tip velocity through the guard.

        Args:
            tip: (3,) m the needle tip now. v_nominal: (3,) m/s commanded tip velocity.
            wound: the throw's registered wound. held: the needle is (or may be) held.
            ready: the needle is held in a grasp a throw starts from (the phase may begin).
            dt: control period (s) the velocity is held for.
        """
        x = np.asarray(tip, dtype=np.float64)
        v = np.array(v_nominal, dtype=np.float64)
        self.observe(held, wound.throw_index)
        center, rotation = wound.ellipsoid_frame()
        axes = self.cbf.semi_axes
        h = float(ellipsoid_h(x, center, axes, rotation))
        if not held:
            self._mode = None
            self._in_flight.clear()
            return GuardResult(False, False, v, v.copy(), False, h, float("nan"), "", False)
        margin = self.margin(dt)
        level = float(margin_level(margin, axes))
        if self.phase == PHASE_IDLE and ready and h >= level:
            self.phase = PHASE_ACTIVE
        active = self.phase == PHASE_ACTIVE
        self._motion.update((center, rotation), dt)
        exceeded = (
            self._motion.speed > self.cbf.tissue_speed_max + _SPEED_TOLERANCE
            or self._motion.acceleration > self.cbf.tissue_acceleration_max + _ACCELERATION_TOLERANCE
        )
        if not self.cbf.enabled:
            return GuardResult(active, True, v, v.copy(), False, h, float("nan"), "", exceeded)
        start = time.perf_counter()
        # The tip's motion relative to the tissue's: holding still is not safe on tissue that moves.
        w = self._motion.point_velocity(x)
        v_rel = v - w
        height = float(surface_height(x, wound.entry_point, wound.surface_normal))
        # A mode may be entered when the tip and every end point still in flight lie in its tightened set.
        may_enter = {
            MODE_WOUND: h >= level and all(wound_ok for wound_ok, _ in self._in_flight),
            MODE_ABOVE: height >= margin and all(above_ok for _, above_ok in self._in_flight),
        }
        candidates = {
            MODE_WOUND: np.asarray(
                self.cbf.filter(x, v_rel, center, rotation, float(dt), margin).v_safe, dtype=np.float64
            ),
            MODE_ABOVE: filter_velocity_surface(
                x, v_rel, wound.entry_point, wound.surface_normal, self.cbf.alpha, float(dt), margin
            )[0],
        }
        allowed = [mode for mode in (MODE_ABOVE, MODE_WOUND) if may_enter[mode]]
        if allowed:
            # The mode whose filtered velocity is nearest the nominal; on a tie, the current one.
            self._mode = min(
                allowed, key=lambda m: (float(np.linalg.norm(candidates[m] - v_rel)), m != self._mode)
            )
        else:
            # The tip in a margin band (or an end point in flight outside both tightened sets): recover by
            # where the tip is, into the ellipsoid only from inside it, else lift. The wound's recovery from
            # outside the ellipsoid heads for its centre through the tissue beside it.
            self._mode = MODE_WOUND if h >= 0.0 else MODE_ABOVE
        v_rel_safe = candidates[self._mode]
        if self.max_tip_speed is not None:
            # A shorter segment of the same direction stays in the (convex) set, relative to the tissue.
            v_rel_safe = v_rel_safe * _speed_share(v_rel_safe, w, self.max_tip_speed)
        intervened = not np.array_equal(v_rel_safe, v_rel)
        v_safe = v_rel_safe + w if intervened else v
        self._record_in_flight(x + v_rel_safe * dt, wound, dt)
        elapsed = time.perf_counter() - start
        return GuardResult(active, True, v, v_safe, intervened, h, elapsed, self._mode, exceeded)

    def jaw_may_hold(self, measured_closure: float, commanded_closure: float) -> bool:
        """Whether the jaw may hold the needle, from its measured and commanded closure (0 open, 1 closed) over
        the last ``latency_steps + 1`` control steps: a reading in ``held_jaw_range``, or a command to close
        (>= 0.5) that may catch the needle while the jaw does not read closed on nothing."""
        low, high = self.held_jaw_range
        self._jaw_window.append(
            low <= measured_closure <= high or (commanded_closure >= 0.5 and measured_closure < high)
        )
        return any(self._jaw_window)

    def filter_target(
        self,
        measured_pose: np.ndarray,
        target_pose: np.ndarray,
        wound: Wound | None,
        grasp: GraspModel,
        dt: float,
        workspace: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, GuardResult]:
        """One control step's target pose through the guard, from kinematics alone.

        Args:
            measured_pose: (10,) the needle holder's measured pose (jaw tip position m, first two rotation
                columns, jaw closure), as the env's ``agent_pos``.
            target_pose: (10,) the commanded target pose, same layout (the env's action).
            wound: the registered wound, or None (no throw to guard: the target passes unchanged).
            grasp: the needle in the jaw. dt: control period (s).
            workspace: (low (3,), high (3,)) m, the box the arm clips target positions to, or None. A filtered
                target outside it would be clipped to a tip end point the filter never checked, so the arm is
                told to keep its measured pose relative to the tissue instead (unturned, carried with the
                tissue's measured velocity, within the box).

        Returns:
            (the target pose to send (10,) float64, the guard's result). While guarding, the position moves so
            that the tip's commanded end point is ``tip + v_safe * dt``, and the rotation columns are those of
            the orthonormalized target rotation (an arm that clips columns to [-1, 1] leaves them as they are).
            A target whose rotation columns are zero or parallel (inside the action space, but no rotation)
            becomes "hold the measured pose", with the target's jaw, filtered like any other target (on tissue
            that moves, holding still is not safe), and a warning says why.

        Raises:
            ValueError: a pose that is not 10 finite numbers, or a measured pose without two independent
                rotation columns.
        """
        pose = finite_vector("measured_pose", measured_pose, 10)
        target = finite_vector("target_pose", target_pose, 10)
        jaw_rot = matrix_from_rot6(pose[3:9])
        no_rotation = False
        try:
            target_rot = matrix_from_rot6(target[3:9])
        except ValueError as error:
            # Held through the filter below: on tissue that moves, holding still is not safe.
            logger.warning(
                "suture_cbf holds the measured pose: the commanded pose has no rotation (%s).", error
            )
            no_rotation = True
            target = target.copy()
            target[:9] = pose[:9]
            target_rot = jaw_rot
        if wound is None:
            nan3 = np.full(3, np.nan)
            return target, GuardResult(
                False, False, nan3, nan3, no_rotation, float("nan"), float("nan"), "", False
            )
        tip_in_jaw = grasp.tip_in_jaw()
        tip = pose[:3] + jaw_rot @ tip_in_jaw
        held = self.jaw_may_hold(float(pose[9]), float(target[9]))
        firm = FIRM_HOLD <= pose[9] <= self.held_jaw_range[1] and target[9] >= FIRM_HOLD
        still = self._last_closure is not None and abs(pose[9] - self._last_closure) < STILL_JAW
        self._measure_tracking(tip, held, firm and still and grasp == self._last_grasp)
        self._last_grasp, self._last_closure = grasp, float(pose[9])
        if held and self.cbf.enabled:
            # No turn while the tip is in a margin band: the lever arm's sweep would work against the recovery.
            turn = 0.0 if self._in_margin_band(tip, wound, dt) else self.max_turn(grasp)
            target_rot = _limit_turn(jaw_rot, target_rot, turn)
        tip_target = target[:3] + target_rot @ tip_in_jaw
        result = self.filter_velocity(tip, (tip_target - tip) / dt, wound, held, held, dt)
        out = target.copy()
        if result.guarding and self.cbf.enabled:
            out[:3] = target[:3] + (result.v_safe - result.v_nominal) * dt
            out[3:9] = np.concatenate([target_rot[:, 0], target_rot[:, 1]])
            if workspace is not None and not np.all((workspace[0] <= out[:3]) & (out[:3] <= workspace[1])):
                # The arm would clip the target to a tip end point the filter never checked. The tip goes
                # with the tissue instead, unturned: where it is relative to the tissue, it stays (unless the
                # box stops the arm following it; the clip below is what the arm would do anyway).
                w = self._motion.point_velocity(tip)
                out[:9] = pose[:9]
                out[:3] = np.clip(out[:3] + w * dt, workspace[0], workspace[1])
                end = out[:3] + jaw_rot @ tip_in_jaw
                self._replace_in_flight(end - w * dt, wound, dt)
                result = result._replace(v_safe=(end - tip) / dt, intervened=True)
        if no_rotation:
            result = result._replace(intervened=True)
        if held:
            self._ends.append(out[:3] + matrix_from_rot6(out[3:9]) @ tip_in_jaw)
        return out, result

    def _record_in_flight(self, end: np.ndarray, wound: Wound, dt: float) -> None:
        """Remember whether a commanded tip end point (3,) m, relative to the tissue, lies in each mode's
        tightened set, for as long as it may stay in flight."""
        if not self.latency_steps:
            return
        center, rotation = wound.ellipsoid_frame()
        margin, axes = self.margin(dt), self.cbf.semi_axes
        in_wound = bool(ellipsoid_h(end, center, axes, rotation) >= margin_level(margin, axes))
        above = float(surface_height(end, wound.entry_point, wound.surface_normal)) >= margin
        self._in_flight.append((in_wound, above))

    def _replace_in_flight(self, end: np.ndarray, wound: Wound, dt: float) -> None:
        """The last commanded end point was replaced by ``end`` (3,) m."""
        if self._in_flight:
            self._in_flight.pop()
        self._record_in_flight(end, wound, dt)

    def _in_margin_band(self, tip: np.ndarray, wound: Wound, dt: float) -> bool:
        """Whether the tip (3,) m lies in neither tightened set: above the tissue by less than the margin and
        not in the tightened ellipsoid."""
        margin = self.margin(dt)
        center, rotation = wound.ellipsoid_frame()
        in_wound = ellipsoid_h(tip, center, self.cbf.semi_axes, rotation) >= margin_level(
            margin, self.cbf.semi_axes
        )
        return not in_wound and surface_height(tip, wound.entry_point, wound.surface_normal) < margin

    def _measure_tracking(self, tip: np.ndarray, held: bool, steady: bool) -> None:
        """The measured tip's distance from the segment it was commanded along: from the tip measured a step
        ago towards the end point commanded ``latency_steps`` steps before that. Measured only across steps in
        which the jaw read closed on the wire and still, was told to stay closed and held the needle in the same
        grasp (``steady``): a needle let go, caught again, or in a loose jaw whose reading cannot tell, follows
        no commanded segment."""
        if not held:
            self._ends.clear()
            self._steady.clear()
            self._last_tip = None
            return
        self._steady.append(steady)
        settled = len(self._steady) == self._steady.maxlen and all(self._steady)
        if settled and self._last_tip is not None and len(self._ends) == self._ends.maxlen:
            self._deviations.append(float(segment_distance(tip, self._last_tip, self._ends[0])))
        self._last_tip = tip.copy()


def _speed_share(v_rel: np.ndarray, w: np.ndarray, max_speed: float) -> float:
    """The largest share s in [0, 1] with |s v_rel + w| <= max_speed (m/s): 1 when already within it, and the
    tissue's own velocity ``w`` (3,) alone when that is faster (s = 0)."""
    v_rel = np.asarray(v_rel, dtype=np.float64)
    if float(np.linalg.norm(v_rel + w)) <= max_speed:
        return 1.0
    a, b, c = float(v_rel @ v_rel), float(v_rel @ w), float(w @ w) - max_speed * max_speed
    if a == 0.0 or c > 0.0:
        return 0.0
    return min(max((-b + math.sqrt(b * b - a * c)) / a, 0.0), 1.0)


def _limit_turn(measured: np.ndarray, target: np.ndarray, max_turn: float) -> np.ndarray:
    """``target`` (3, 3), or the rotation ``max_turn`` rad from ``measured`` (3, 3) towards it where it is
    farther."""
    rotvec = rotvec_from_matrix(measured.T @ target)
    angle = float(np.linalg.norm(rotvec))
    if angle <= max_turn:
        return target
    return measured @ matrix_from_rotvec(rotvec * (max_turn / angle))
