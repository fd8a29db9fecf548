"""The CBF over one suture throw, from what a real system measures: one filter for the env and the robot path.

:class:`TipGuard` holds the throw's phase (idle, active, done) and applies
:meth:`CBFConfig.filter <lerobot_suture.safety.cbf_config.CBFConfig.filter>` to the needle tip's motion. It
is used two ways, with the same phase rules and the same filter:

- :meth:`TipGuard.filter_target` (the robot path, ``suture_cbf`` processor step): from the measured pose of
  the needle holder, the commanded target pose, a :class:`GraspModel` (where the needle sits in the jaw) and a
  registered :class:`Wound` (entry and exit points, tissue normal). The needle tip and the commanded tip
  motion come from kinematics; whether the needle is held comes from the measured jaw closure, whether it is
  in tissue from the needle's arc against the tissue surface. It returns the target pose moved so that the
  tip's commanded end point is ``tip + v_safe * control_dt``. Nothing is read from a simulator.
- :meth:`TipGuard.filter_velocity` (the env path, ``CBFActionWrapper``): the env hands over the tip and its
  nominal velocity at the moment its controller computes them, and the grasp and tissue signals it knows.

Why a target end point is safe under latency: the discrete filter keeps the commanded segment, hence its end
point, in the margin-tightened ellipsoid, which is convex. An arm that moves the tip in a straight line towards
each commanded end point (``SutureEnv(tip_tracking=True)``, or a real arm's Cartesian controller) therefore
stays within its tracking error of that convex set whichever stale pose the command was computed from, and
whether it reaches the end point or falls short. The margin must cover tracking error plus grasp-model error.
Units: m, s, rad.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from lerobot_suture.safety.cbf import ellipsoid_h, suture_ellipsoid_frame
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.sim.geometry import NEEDLE_RADIUS, grasp_transform, matrix_from_rot6, needle_arc_points
from lerobot_suture.sim.task import GRASP_ANGLE

PHASE_IDLE = "idle"
"""No throw yet: motions pass through."""
PHASE_ACTIVE = "active"
"""A throw has begun: motions are filtered."""
PHASE_DONE = "done"
"""The throw ended (needle out of the tissue, or released): motions pass through until the next throw."""

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
        """(centre (3,) m, world-from-ellipsoid rotation (3, 3)) of the throw's safe set."""
        return self._frame

    def depth(self, points: np.ndarray) -> np.ndarray:
        """Depth (m) of ``points`` (..., 3) below the tissue surface plane (negative above it)."""
        return (self.entry_point - np.asarray(points, dtype=np.float64)) @ self.surface_normal


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
        active: the filter was applied (phase ``active``).
        v_nominal: (3,) m/s commanded tip velocity.
        v_safe: (3,) m/s tip velocity let through.
        intervened: ``v_safe`` differs from ``v_nominal``.
        h: barrier at the tip (>= 0 inside the safe set), NaN without a wound.
        filter_time: wall time of the filter call (s), NaN when not active.
    """

    active: bool
    v_nominal: np.ndarray
    v_safe: np.ndarray
    intervened: bool
    h: float
    filter_time: float


@dataclass
class TipGuard:
    """The phase of a throw and the CBF on the needle tip's motion (see the module docstring).

    Phase rules: the filter switches on at the first control step where the needle is held in a grasp a throw
    starts from and the tip is inside the set (the margin-tightened set in discrete mode); it switches off for
    the rest of the throw when the needle leaves the tissue after having been in it, or is released. A new
    ``throw_index`` starts over; so does :meth:`reset`.

    Args:
        cbf: the filter's configuration (``enabled=False``: the phase and h are tracked, motions pass).
        held_jaw_range: measured jaw closures (0 open, 1 closed) that mean "the jaw holds the needle": a jaw
            closed on the wire reads about 0.88, one closed on nothing 1 (:meth:`filter_target` only).
    """

    cbf: CBFConfig = field(default_factory=lambda: CBFConfig(enabled=True))
    held_jaw_range: tuple[float, float] = (0.6, 0.97)

    def __post_init__(self):
        low, high = self.held_jaw_range
        if not 0.0 <= low < high <= 1.0:
            raise ValueError(
                f"`held_jaw_range` must satisfy 0 <= low < high <= 1. Got {self.held_jaw_range}."
            )
        self.reset()

    def reset(self) -> None:
        """Forget the throw: back to ``idle``."""
        self.phase = PHASE_IDLE
        self._throw_index: int | None = None
        self._seen_in_tissue = False

    @property
    def activation_level(self) -> float:
        return self.cbf.margin_level if self.cbf.discrete else 0.0

    def observe(self, held: bool, in_tissue: bool) -> None:
        """The throw's end: the needle is out of the tissue after having been in it, or not held."""
        if self.phase != PHASE_ACTIVE:
            return
        if in_tissue:
            self._seen_in_tissue = True
        elif self._seen_in_tissue:
            self.phase = PHASE_DONE
        if not held:
            self.phase = PHASE_DONE

    def filter_velocity(
        self, tip: np.ndarray, v_nominal: np.ndarray, wound: Wound, ready: bool, in_tissue: bool, dt: float
    ) -> GuardResult:
        """One control step's tip velocity through the guard.

        Args:
            tip: (3,) m the needle tip now. v_nominal: (3,) m/s commanded tip velocity.
            wound: the throw's registered wound. ready: the needle is held in a grasp a throw starts from.
            in_tissue: the needle is in tissue now. dt: control period (s) the velocity is held for.
        """
        x = np.asarray(tip, dtype=np.float64)
        v = np.array(v_nominal, dtype=np.float64)
        if wound.throw_index != self._throw_index:
            self.reset()
            self._throw_index = wound.throw_index
        center, rotation = wound.ellipsoid_frame()
        axes = self.cbf.semi_axes
        h = float(ellipsoid_h(x, center, axes, rotation))
        if self.phase == PHASE_IDLE and ready and h >= self.activation_level:
            self.phase = PHASE_ACTIVE
            self._seen_in_tissue = bool(in_tissue)
        active = self.phase == PHASE_ACTIVE
        if active and self.cbf.enabled:
            start = time.perf_counter()
            result = self.cbf.filter(x, v, center, rotation, float(dt))
            elapsed = time.perf_counter() - start
            return GuardResult(
                True, v, np.asarray(result.v_safe, dtype=np.float64), bool(result.intervened), h, elapsed
            )
        return GuardResult(active, v, v.copy(), False, h, float("nan"))

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
            (the target pose to send (10,) float64, the guard's result). While active, the position moves so
            that the tip's commanded end point is ``tip + v_safe * dt``, and the rotation columns are those of
            the orthonormalized target rotation (an arm that clips columns to [-1, 1] leaves them as they are).

        Raises:
            ValueError: a pose that is not 10 finite numbers with two independent rotation columns.
        """
        pose = _finite_vector("measured_pose", measured_pose, 10)
        target = _finite_vector("target_pose", target_pose, 10)
        jaw_rot = matrix_from_rot6(pose[3:9])
        target_rot = matrix_from_rot6(target[3:9])
        if wound is None:
            nan3 = np.full(3, np.nan)
            return target, GuardResult(False, nan3, nan3, False, float("nan"), float("nan"))
        arc_in_jaw = grasp.arc_in_jaw()
        arc = pose[:3] + arc_in_jaw @ jaw_rot.T
        tip = arc[0]
        held = self.held_jaw_range[0] <= pose[9] <= self.held_jaw_range[1]
        in_tissue = bool(np.any(wound.depth(arc) > 0.0))
        if wound.throw_index == self._throw_index:
            self.observe(held, in_tissue)
        tip_target = target[:3] + target_rot @ arc_in_jaw[0]
        result = self.filter_velocity(tip, (tip_target - tip) / dt, wound, held, in_tissue, dt)
        out = target.copy()
        if result.active:
            out[:3] = target[:3] + (result.v_safe - result.v_nominal) * dt
            out[3:9] = np.concatenate([target_rot[:, 0], target_rot[:, 1]])
            if workspace is not None and not np.all((workspace[0] <= out[:3]) & (out[:3] <= workspace[1])):
                out[:9] = pose[:9]
        return out, result
