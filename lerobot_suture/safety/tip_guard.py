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
switches mode only while the tip and every end point it commanded in the last ``latency_steps`` control steps
lie in both sets (their intersection is convex), choosing the mode whose filtered velocity is nearest the
nominal one. Why this covers latency and an arm that falls short: an arm that moves the tip in straight lines
towards commanded end points keeps it in the convex hull of where it was and of those end points. Within a mode
that hull is inside the mode's set; at a switch every end point still in flight, and the tip, lie in the
intersection, which is inside the new mode's set too. The margin covers the tip's distance from that path
(tracking error plus grasp-model error); a tip found in a margin band is brought back by the mode's own
recovery rule (its barrier never decreases over the step).

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
import time
from collections import deque
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from lerobot_suture.safety.cbf import ellipsoid_h, suture_ellipsoid_frame
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.safety.surface_cbf import filter_velocity_surface, surface_height
from lerobot_suture.sim.geometry import NEEDLE_RADIUS, grasp_transform, matrix_from_rot6, needle_arc_points
from lerobot_suture.sim.task import GRASP_ANGLE

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

_ARC_POINTS = 16


def _finite_vector(name: str, value, size: int) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64).reshape(-1)
    if v.shape != (size,) or not np.all(np.isfinite(v)):
        raise ValueError(f"`{name}` must be {size} finite numbers. Got {np.asarray(value).tolist()!r}.")
    return v


@dataclass(frozen=True)
class Wound:
    """A registered wound: where the throw enters and leaves the tissue (world, m).

    Args:
        entry_point: (3,) the marked entry point on the tissue surface.
        exit_point: (3,) the marked exit point; apart from the entry along the surface.
        surface_normal: (3,) the tissue surface normal, out of the tissue (any length > 0).
        throw_index: which throw of a running suture it is (a new index starts a new throw).
    """

    entry_point: np.ndarray
    exit_point: np.ndarray
    surface_normal: np.ndarray
    throw_index: int = 0

    def __post_init__(self):
        entry = _finite_vector("entry_point", self.entry_point, 3)
        exit_ = _finite_vector("exit_point", self.exit_point, 3)
        normal = _finite_vector("surface_normal", self.surface_normal, 3)
        if np.linalg.norm(normal) < 1e-9:
            raise ValueError(
                "`surface_normal` must be a non-zero vector (the tissue normal, out of the tissue)."
            )
        object.__setattr__(self, "entry_point", entry)
        object.__setattr__(self, "exit_point", exit_)
        object.__setattr__(self, "surface_normal", normal / np.linalg.norm(normal))
        # Computed once (it raises when entry and exit are not apart on the surface): the guard and the
        # env wrapper read it several times per control step.
        object.__setattr__(self, "_frame", suture_ellipsoid_frame(entry, exit_, normal))

    def ellipsoid_frame(self) -> tuple[np.ndarray, np.ndarray]:
        """(centre (3,) m, world-from-ellipsoid rotation (3, 3)) of the throw's ellipsoid."""
        return self._frame

    def barrier(self, points: np.ndarray, semi_axes: np.ndarray) -> np.ndarray:
        """The safe set's barrier at ``points`` (..., 3) m for an ellipsoid of ``semi_axes`` (3,) m: the larger of
        the ellipsoid's h and the height above the tissue surface in units of the normal semi-axis. >= 0
        exactly where the tip may be (above the tissue, or in the ellipsoid); (...,) float64."""
        center, rotation = self._frame
        h = np.asarray(ellipsoid_h(points, center, semi_axes, rotation))
        height = surface_height(points, self.entry_point, self.surface_normal) / semi_axes[2]
        return np.maximum(h, height)


@dataclass
class GraspModel:
    """Where the needle sits in the jaw (the grasp model; ``geometry.grasp_transform``), draccus-compatible.

    Args:
        angle: arc angle of the grasp point (rad), in (0, pi).
        offset_along_jaw: shift of the needle along the jaw axis (m), |offset| <= 5 mm.
        roll: tilt of the needle about the jaw's x axis (rad), |roll| <= 0.5.
        radius: needle radius (m), > 0.
    """

    angle: float = GRASP_ANGLE
    offset_along_jaw: float = 0.0
    roll: float = 0.0
    radius: float = NEEDLE_RADIUS

    def __post_init__(self):
        checks = {
            "angle": (0.0, np.pi, self.angle),
            "offset_along_jaw": (-0.005, 0.005, self.offset_along_jaw),
            "roll": (-0.5, 0.5, self.roll),
            "radius": (1e-4, 0.1, self.radius),
        }
        for name, (low, high, value) in checks.items():
            if isinstance(value, bool) or not isinstance(value, int | float) or not low <= value <= high:
                raise ValueError(f"`{name}` must be a number in [{low}, {high:.4g}]. Got {value!r}.")

    def needle_in_jaw(self) -> tuple[np.ndarray, np.ndarray]:
        """(position (3,) m, rotation (3, 3)) of the needle frame in the jaw-tip frame."""
        return grasp_transform(self.angle, self.offset_along_jaw, self.roll, self.radius)

    def arc_in_jaw(self, n_points: int = _ARC_POINTS) -> np.ndarray:
        """(n, 3) m points along the needle in the jaw-tip frame, tip first."""
        position, rotation = self.needle_in_jaw()
        return position + needle_arc_points(n_points, self.radius) @ rotation.T

    def tip_in_jaw(self) -> np.ndarray:
        """(3,) m the needle tip in the jaw-tip frame."""
        return self.arc_in_jaw(2)[0]


class GuardResult(NamedTuple):
    """What the guard did with one control step's motion.

    Attributes:
        active: the throw's phase is ``active`` (the throw has begun and the needle is held).
        guarding: the needle may be held and a wound is registered: the filter was applied (or, disabled, would
            have been).
        v_nominal: (3,) m/s commanded tip velocity.
        v_safe: (3,) m/s tip velocity let through.
        intervened: ``v_safe`` differs from ``v_nominal``.
        h: the ellipsoid's barrier at the tip (>= 0 inside it), NaN without a wound.
        filter_time: wall time of the filter call (s), NaN when it did not run.
        mode: ``above`` or ``wound``, the convex set the step was kept in ("" when not guarding).
    """

    active: bool
    guarding: bool
    v_nominal: np.ndarray
    v_safe: np.ndarray
    intervened: bool
    h: float
    filter_time: float
    mode: str


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
    """

    cbf: CBFConfig = field(default_factory=lambda: CBFConfig(enabled=True))
    held_jaw_range: tuple[float, float] = (0.45, 0.97)
    latency_steps: int = 0

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

    @property
    def activation_level(self) -> float:
        return self.cbf.margin_level if self.cbf.discrete else 0.0

    @property
    def mode(self) -> str | None:
        """``above`` or ``wound`` while guarding, else None."""
        return self._mode

    @property
    def throw_index(self) -> int | None:
        """The throw the phase is of (None before the first)."""
        return self._throw_index

    def observe(self, held: bool, throw_index: int | None = None) -> None:
        """After a step: a needle no longer held ends the throw's phase; a new ``throw_index`` starts over."""
        if throw_index is not None and throw_index != self._throw_index:
            self.reset()
            self._throw_index = throw_index
        if self.phase == PHASE_ACTIVE and not held:
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
        h = float(ellipsoid_h(x, center, self.cbf.semi_axes, rotation))
        if not held:
            self._mode = None
            self._in_flight.clear()
            return GuardResult(False, False, v, v.copy(), False, h, float("nan"), "")
        if self.phase == PHASE_IDLE and ready and h >= self.activation_level:
            self.phase = PHASE_ACTIVE
        active = self.phase == PHASE_ACTIVE
        if not self.cbf.enabled:
            return GuardResult(active, True, v, v.copy(), False, h, float("nan"), "")
        start = time.perf_counter()
        margin = self.cbf.margin if self.cbf.discrete else 0.0
        height = float(surface_height(x, wound.entry_point, wound.surface_normal))
        # A mode may be entered when the tip and every end point still in flight lie in its set: the tightened
        # ellipsoid; above the tissue (a tip in the surface's margin band is lifted by the mode's recovery).
        may_enter = {
            MODE_WOUND: h >= self.activation_level and all(wound_ok for wound_ok, _ in self._in_flight),
            MODE_ABOVE: height >= margin and all(above_ok for _, above_ok in self._in_flight),
        }
        candidates = {
            MODE_WOUND: np.asarray(
                self.cbf.filter(x, v, center, rotation, float(dt)).v_safe, dtype=np.float64
            ),
            MODE_ABOVE: filter_velocity_surface(
                x, v, wound.entry_point, wound.surface_normal, self.cbf.alpha, float(dt), margin
            )[0],
        }
        allowed = [mode for mode in (MODE_ABOVE, MODE_WOUND) if may_enter[mode] or mode == self._mode]
        if allowed:
            # The mode whose filtered velocity is nearest the nominal; on a tie, the current one.
            self._mode = min(
                allowed, key=lambda m: (float(np.linalg.norm(candidates[m] - v)), m != self._mode)
            )
        else:  # no mode yet, the tip in the tissue outside the tightened ellipsoid: back into it, or lift
            self._mode = MODE_WOUND if h >= 0.0 else MODE_ABOVE
        v_safe = candidates[self._mode]
        if self.latency_steps:
            end = x + v_safe * dt
            self._in_flight.append(
                (
                    bool(ellipsoid_h(end, center, self.cbf.semi_axes, rotation) >= self.activation_level),
                    float(surface_height(end, wound.entry_point, wound.surface_normal)) >= margin,
                )
            )
        elapsed = time.perf_counter() - start
        intervened = not np.array_equal(v_safe, v)
        return GuardResult(active, True, v, v_safe, intervened, h, elapsed, self._mode)

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
                told to hold its measured pose instead.

        Returns:
            (the target pose to send (10,) float64, the guard's result). While guarding, the position moves so
            that the tip's commanded end point is ``tip + v_safe * dt``, and the rotation columns are those of
            the orthonormalized target rotation (an arm that clips columns to [-1, 1] leaves them as they are).
            A target whose rotation columns are zero or parallel (inside the action space, but no rotation)
            becomes "hold the measured pose", with the target's jaw, and a warning says why.

        Raises:
            ValueError: a pose that is not 10 finite numbers, or a measured pose without two independent
                rotation columns.
        """
        pose = _finite_vector("measured_pose", measured_pose, 10)
        target = _finite_vector("target_pose", target_pose, 10)
        jaw_rot = matrix_from_rot6(pose[3:9])
        try:
            target_rot = matrix_from_rot6(target[3:9])
        except ValueError as error:
            logger.warning(
                "suture_cbf holds the measured pose: the commanded pose has no rotation (%s).", error
            )
            held_target = target.copy()
            held_target[:9] = pose[:9]
            nan3 = np.full(3, np.nan)
            return held_target, GuardResult(False, False, nan3, nan3, True, float("nan"), float("nan"), "")
        if wound is None:
            nan3 = np.full(3, np.nan)
            return target, GuardResult(False, False, nan3, nan3, False, float("nan"), float("nan"), "")
        tip_in_jaw = grasp.tip_in_jaw()
        tip = pose[:3] + jaw_rot @ tip_in_jaw
        held = self.jaw_may_hold(float(pose[9]), float(target[9]))
        tip_target = target[:3] + target_rot @ tip_in_jaw
        result = self.filter_velocity(tip, (tip_target - tip) / dt, wound, held, held, dt)
        out = target.copy()
        if result.guarding and self.cbf.enabled:
            out[:3] = target[:3] + (result.v_safe - result.v_nominal) * dt
            out[3:9] = np.concatenate([target_rot[:, 0], target_rot[:, 1]])
            if workspace is not None and not np.all((workspace[0] <= out[:3]) & (out[:3] <= workspace[1])):
                out[:9] = pose[:9]
        return out, result
