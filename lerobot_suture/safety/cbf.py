r"""Model-free control barrier function (CBF) on an ellipsoidal safe set around the wound.

Pure numpy, no simulator. Every function takes the needle-tip position ``x`` as ``(3,)`` or
``(..., 3)`` (metres, world frame) and broadcasts over the leading axes. Velocities are in m/s, times
in s. The formulas are written once, on vector components: a single (3,) state evaluates them on
Python floats (microseconds per call), a batch on numpy arrays (millions of states per second); both
are the same sequence of IEEE operations and give identical bits.

Barrier (the paper's ellipsoid)
-------------------------------
The safe set is the ellipsoid S = {x : h(x) >= 0} with centre ``c`` (m), semi-axes ``a`` (m) and an
optional orientation ``R`` (3x3, world-from-ellipsoid; identity when omitted)::

    D     = x - c                      # (..., 3) world
    E     = R^T D                      # (..., 3) in the ellipsoid frame
    h(x)  = 1 - sum_i E_i^2 / a_i^2    # 1 at the centre, 0 on the surface, < 0 outside
    dh/dx = -2 R (E / a^2)             # (..., 3) 1/m
    n(x)  = (dh/dx) / |dh/dx|          # unit inward normal

The centre: there dh/dx = 0 and ``n`` is undefined. We define n = 0 wherever the scaled radius
|E / a| is below 1e-12 (there h rounds to exactly 1.0 in float64): the constraint below reads
0 >= -alpha, always true, so the filter passes the nominal velocity unchanged. This is exact for the
continuous condition (dh/dt = dh/dx . v = 0 at the centre, whatever v).

Continuous-time filter (the paper, after Molnar et al. 2021)
------------------------------------------------------------
The safe velocity must satisfy ``n . v_s >= -alpha h(x)``; the minimum-norm change of the nominal
velocity ``v_n`` that does so (the solution of the QP min |v - v_n|^2 s.t. that one linear
constraint) is the closed form::

    v_s = v_n + max(-n . v_n - alpha h(x), 0) n          (:func:`filter_velocity`)

Units: ``n`` is unit-free, so ``alpha h`` is a speed: the paper's ``alpha`` is 1/s times an
implicit 1 m length scale. For a set a centimetre across it allows outward speeds of order
``alpha`` m/s deep inside, i.e. it only binds right at the boundary.

The discrete-time gap, and what we do about it (:func:`filter_velocity_discrete`)
-------------------------------------------------------------------------------
The env holds one Cartesian tip velocity for a whole control step ``dt`` (0.1 s) while physics runs
at 2 ms. The continuous condition constrains only the rate at the start of the step; over the step a
tangential velocity leaves a curved boundary (h drops by |A^-1 R^T v|^2 dt^2), and the paper's
``alpha h`` allows an outward step of ``alpha h dt`` metres, for alpha of order 1/s far more than the
size of a centimetre ellipsoid. So the filter
used in the env enforces the exact discrete-time CBF condition (Agrawal & Sreenath 2017) on the end
point of the step, for a barrier tightened by a tracking margin::

    h~(x)         = h(x) - h_m,        h_m = 1 - (1 - m / min(a))^2
    h~(x + v dt) >= (1 - gamma) h~(x), gamma = min(alpha dt, 1)

Why this keeps h >= 0 at every physics step: with perfect tracking the tip moves on the segment
x -> x + v dt; h is concave (a negative semi-definite quadratic), so its minimum over the segment is
at an end point, and both end points have h~ >= 0 once h~(x) >= 0 (then by induction over steps).
The margin covers tracking error: {h~ >= 0} is the ellipsoid shrunk about its centre by the factor
``rho = 1 - m / min(a)``, and a displacement of at most ``m`` metres changes the scaled radius
|A^-1 R^T (x - c)| by at most ``m / min(a)``, so every point within ``m`` metres of such a commanded
segment is in S: h >= 0 at every physics step as long as the tip tracks the command to within ``m``.
(Shrinking each semi-axis by ``m`` instead would not be enough on an elongated ellipsoid.) A step that
starts in the margin band because of tracking error is handled by the recovery rule below.

That premise is the velocity controller's (the paper's lambda > alpha, in discrete form): the env's
tip-first inverse kinematics (``lerobot_suture.sim.controller.tip_first_velocity_ik``) keeps it for any
command, rotation included, and ``CBFActionWrapper`` measures it every step (``cbf_segment_deviation``).

Here ``alpha`` is a true rate in 1/s: h~ may decay by at most a factor ``1 - alpha dt`` per step, so
the tip slows down geometrically as it approaches the tightened boundary.

The condition is enforced in closed form, in two steps (no iterative solver: vectorized, microseconds):

1. Linearize the end point, h~(x + v dt) ~ h~(x) + dt dh/dx . v, and apply the paper's closed form to
   the resulting half-space ``n . v >= -gamma h~(x) / (dt |dh/dx|)`` (the unit-consistent form of
   the paper's constraint), giving ``v_c``. At the centre there is no constraint (n = 0).
2. Along ``v_c`` the end point is exactly quadratic, ``f(s) = h~(x + s v_c dt) = h~ + s b - s^2 q``
   with ``b = dt dh/dx . v_c`` and ``q = dt^2 |A^-1 R^T v_c|^2``; take the largest step fraction
   ``s`` in [0, 1] with ``f(s) >= (1 - gamma) h~(x)`` (a root of the quadratic) and return
   ``v_s = s v_c``. Since q >= 0, a nominal velocity that already meets the exact condition also meets
   the linearized one, so it is returned unchanged (minimal intervention). The result is not the exact
   minimum-norm solution of the quadratic constraint; it differs only by the curvature term.

If h~(x) < 0 (the tip is in the margin band or outside, from tracking error or because the filter was
switched on there), the condition asks h~ to rise by ``gamma |h~|``; step 1 adds an inward component,
and if step 2 cannot reach the target along ``v_c`` it takes the ``s`` that maximizes ``f``, so h~
never decreases over the step.

Filtering at the physics rate instead would need the env's inner loop to re-filter every 2 ms; the
end-point condition needs nothing from the env but the control period.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

_ORIGIN = np.zeros(3)
_CENTRE_R2 = 1e-24
"""Squared scaled radius |E / a|^2 below which a point counts as the centre (h == 1.0 in float64)."""


class CBFResult(NamedTuple):
    """What a filter call did, per state (Python scalars for a single (3,) state).

    Attributes:
        v_safe: (..., 3) safe velocity (m/s), world frame.
        h: (...,) barrier value at ``x`` for the safe set itself (no margin); < 0 outside.
        intervened: (...,) bool, True where ``v_safe`` differs from the nominal velocity.
        correction: (...,) speed (m/s) added along the inward normal by the closed form (>= 0).
        step_scale: (...,) fraction in [0, 1] of the corrected velocity kept by the discrete-time
            step-length limit (always 1 for :func:`filter_velocity`).
    """

    v_safe: np.ndarray
    h: Any
    intervened: Any
    correction: Any
    step_scale: Any


# One implementation of the math, written on vector components (each a float or a numpy array) and
# a table of the four non-arithmetic operations it needs. A single (3,) state runs it on Python
# floats (a few microseconds); batches run it on numpy arrays. The two give identical bits: both are
# the same sequence of IEEE double operations.


class _Ops(NamedTuple):
    sqrt: Callable
    where: Callable
    maximum: Callable
    minimum: Callable


_FLOAT_OPS = _Ops(
    math.sqrt,
    lambda cond, a, b: a if cond else b,
    lambda a, b: b if b > a else a,  # NaN in ``a`` propagates, as in np.maximum (``b`` is never NaN)
    lambda a, b: b if b < a else a,
)
_ARRAY_OPS = _Ops(np.sqrt, np.where, np.maximum, np.minimum)


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _to_frame(r, v):
    """World -> ellipsoid frame, R^T v (r: rows of R, or None for identity)."""
    if r is None:
        return v
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = r
    v0, v1, v2 = v
    return (r00 * v0 + r10 * v1 + r20 * v2, r01 * v0 + r11 * v1 + r21 * v2, r02 * v0 + r12 * v1 + r22 * v2)


def _to_world(r, v):
    """Ellipsoid frame -> world, R v."""
    if r is None:
        return v
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = r
    v0, v1, v2 = v
    return (r00 * v0 + r01 * v1 + r02 * v2, r10 * v0 + r11 * v1 + r12 * v2, r20 * v0 + r21 * v1 + r22 * v2)


def _barrier_terms(x, c, a, r):
    """g = R (E / a^2) = -(dh/dx) / 2 in the world frame (1/m), r2 = |E / a|^2 (h = 1 - r2), 1 / a^2."""
    e = _to_frame(r, (x[0] - c[0], x[1] - c[1], x[2] - c[2]))  # tip in the ellipsoid frame (m)
    inv_a2 = (1.0 / (a[0] * a[0]), 1.0 / (a[1] * a[1]), 1.0 / (a[2] * a[2]))
    g = (e[0] * inv_a2[0], e[1] * inv_a2[1], e[2] * inv_a2[2])
    return _to_world(r, g), _dot(e, g), inv_a2


def _inward_normal(ops, g, r2):
    """Unit inward normal -g / |g| (zero at the centre), |g|, and the centre mask."""
    centre = r2 <= _CENTRE_R2
    g_norm = ops.sqrt(_dot(g, g))
    scale = ops.where(centre, 0.0, -1.0 / ops.where(centre, 1.0, g_norm))
    return (g[0] * scale, g[1] * scale, g[2] * scale), g_norm, centre


def _closed_form(ops, v, n, rhs):
    """Minimum-norm velocity with n . v >= rhs for unit n: v + max(rhs - n . v, 0) n.

    Returns ``v`` itself, bit for bit, where it already satisfies the constraint.
    """
    correction = ops.maximum(rhs - _dot(n, v), 0.0)  # m/s
    return (v[0] + correction * n[0], v[1] + correction * n[1], v[2] + correction * n[2]), correction


def _margin_level(ops, margin, a):
    rho = 1.0 - margin / ops.minimum(ops.minimum(a[0], a[1]), a[2])
    return 1.0 - rho * rho


def _continuous(ops, x, v, c, a, r, alpha):
    g, r2, _ = _barrier_terms(x, c, a, r)
    h = 1.0 - r2
    n, _, _ = _inward_normal(ops, g, r2)
    v_safe, correction = _closed_form(ops, v, n, -alpha * h)
    return v_safe, h, correction > 0.0, correction, 1.0


def _discrete(ops, x, v, c, a, r, alpha, dt, margin):
    gamma = min(alpha * dt, 1.0)
    g, r2, inv_a2 = _barrier_terms(x, c, a, r)
    h = 1.0 - r2
    h_tight = h - _margin_level(ops, margin, a)
    n, g_norm, centre = _inward_normal(ops, g, r2)
    # 1. Closed form on the linearized end-point condition dt dh/dx . v >= -gamma h_tight, dh/dx = 2|g| n.
    rhs = ops.where(centre, -math.inf, -gamma * h_tight / (2.0 * dt * ops.where(centre, 1.0, g_norm)))
    v_c, correction = _closed_form(ops, v, n, rhs)
    # 2. Exact end point along v_c: f(s) = h_tight + s b - s^2 q.
    step = (v_c[0] * dt, v_c[1] * dt, v_c[2] * dt)  # m
    b = -2.0 * _dot(g, step)
    step_e = _to_frame(r, step)
    q = (
        step_e[0] * step_e[0] * inv_a2[0]
        + step_e[1] * step_e[1] * inv_a2[1]
        + step_e[2] * step_e[2] * inv_a2[2]
    )
    positive_q = q > 0.0
    q_safe = ops.where(positive_q, q, 1.0)
    s_peak = ops.where(
        positive_q, ops.minimum(ops.maximum(0.5 * b / q_safe, 0.0), 1.0), ops.where(b >= 0.0, 1.0, 0.0)
    )
    target = ops.minimum((1.0 - gamma) * h_tight, h_tight + s_peak * (b - s_peak * q))
    slack = h_tight - target
    root = ops.sqrt(ops.maximum(b * b + 4.0 * q * slack, 0.0))
    # Larger root of q s^2 - b s - slack = 0, in the cancellation-free form for each sign of b.
    den = root - b
    s_root = ops.where(b >= 0.0, (b + root) / (2.0 * q_safe), 2.0 * slack / ops.where(den > 0.0, den, 1.0))
    s = ops.where(h_tight + b - q >= target, 1.0, ops.minimum(ops.maximum(s_root, 0.0), 1.0))
    v_safe = (s * v_c[0], s * v_c[1], s * v_c[2])
    return v_safe, h, (correction > 0.0) | (s < 1.0), correction, s


# Input handling: validation and the float / array dispatch.


def _check_positive(name: str, value: float) -> float:
    value = float(value)
    if not value > 0.0 or not math.isfinite(value):
        raise ValueError(f"`{name}` must be > 0 and finite. Got {value}.")
    return value


_NAMES = ("x", "center", "axes", "v_nominal")


def _prepare(x, v, center, axes, rotation, margin=None):
    """Validate; return (ops, batch shape or None for one state, components of x, c, a[, v], rows of R)."""
    arrays = [np.asarray(x, dtype=np.float64), np.asarray(center, dtype=np.float64)]
    arrays.append(np.asarray(axes, dtype=np.float64))
    if v is not None:
        arrays.append(np.asarray(v, dtype=np.float64))
    if rotation is not None:
        rotation = np.asarray(rotation, dtype=np.float64)
    single = (
        arrays[0].shape == arrays[1].shape == arrays[2].shape == (3,)
        and (v is None or arrays[3].shape == (3,))
        and (rotation is None or rotation.shape == (3, 3))
    )
    if single:  # the common case of one state, kept cheap
        comps = [arr.tolist() for arr in arrays]
        a0, a1, a2 = comps[2]
        axes_ok = 0.0 < a0 < math.inf and 0.0 < a1 < math.inf and 0.0 < a2 < math.inf  # False for NaN
        a_min = min(comps[2])
    else:
        for name, arr in zip(_NAMES, arrays, strict=False):
            if arr.shape[-1:] != (3,):
                raise ValueError(f"`{name}` must have shape (3,) or (..., 3). Got shape {arr.shape}.")
        if rotation is not None and rotation.shape[-2:] != (3, 3):
            raise ValueError(f"`rotation` must have shape (3, 3) or (..., 3, 3). Got shape {rotation.shape}.")
        # Shared (3,) parameters become Python floats here too.
        comps = [arr.tolist() if arr.ndim == 1 else (arr[..., 0], arr[..., 1], arr[..., 2]) for arr in arrays]
        axes_ok = bool(((arrays[2] > 0.0) & (arrays[2] < math.inf)).all())
        a_min = arrays[2].min()
    if not axes_ok:
        raise ValueError(f"`axes` must be > 0 and finite (semi-axes in m). Got {arrays[2].tolist()}.")
    if margin is not None and not 0.0 <= margin < a_min:
        raise ValueError(
            f"`margin` must be in [0, min(axes)) m. Got {margin} with axes {arrays[2].tolist()}."
        )
    if rotation is None:
        rows = None
    elif rotation.ndim == 2:
        rows = rotation.tolist()
    else:
        rows = [[rotation[..., i, j] for j in range(3)] for i in range(3)]
    if single:
        return _FLOAT_OPS, None, comps, rows
    shapes = [arr.shape[:-1] for arr in arrays]
    if rotation is not None:
        shapes.append(rotation.shape[:-2])
    return _ARRAY_OPS, np.broadcast_shapes(*shapes), comps, rows


def _result(batch_shape, v_safe, h, intervened, correction, step_scale) -> CBFResult:
    if batch_shape is None:
        return CBFResult(np.array(v_safe), h, bool(intervened), correction, step_scale)
    out = np.empty(batch_shape + (3,))
    out[..., 0], out[..., 1], out[..., 2] = v_safe
    zeros = np.zeros(batch_shape)
    return CBFResult(
        out,
        h + zeros,
        np.broadcast_to(intervened, batch_shape).copy(),
        correction + zeros,
        step_scale + zeros,
    )


# Public API.


def ellipsoid_h(x, center, axes, rotation=None):
    """Barrier value h = 1 - sum_i E_i^2 / a_i^2 with E = R^T (x - center).

    Args:
        x: (3,) or (..., 3) needle-tip position (m), world frame.
        center: (3,) or (..., 3) ellipsoid centre (m), world frame.
        axes: (3,) or (..., 3) semi-axes (m), all > 0, along the ellipsoid frame's axes.
        rotation: optional (3, 3) or (..., 3, 3) world-from-ellipsoid rotation; identity if None.

    Returns:
        (...,) float64 array (a float for a single state): 1 at the centre, 0 on the surface,
        negative outside.

    Raises:
        ValueError: if ``axes`` are not all positive and finite, or a shape is wrong.
    """
    ops, batch_shape, (x, c, a), rows = _prepare(x, None, center, axes, rotation)
    _, r2, _ = _barrier_terms(x, c, a, rows)
    return 1.0 - r2 if batch_shape is None else 1.0 - r2 + np.zeros(batch_shape)


def ellipsoid_grad_h(x, center, axes, rotation=None) -> np.ndarray:
    """Gradient dh/dx = -2 R (E / a^2), (..., 3) in 1/m, world frame; zero at the centre."""
    ops, batch_shape, (x, c, a), rows = _prepare(x, None, center, axes, rotation)
    g, _, _ = _barrier_terms(x, c, a, rows)
    out = np.empty((batch_shape or ()) + (3,))
    out[..., 0], out[..., 1], out[..., 2] = (-2.0 * g[0], -2.0 * g[1], -2.0 * g[2])
    return out


def inward_normal(x, center, axes, rotation=None) -> np.ndarray:
    """Unit inward normal n = (dh/dx) / |dh/dx|, (..., 3) world frame.

    At the centre (scaled radius below 1e-12, where the gradient vanishes) n is defined as the zero
    vector, which makes the CBF constraint trivially satisfied there.

    Args:
        x, center, axes, rotation: as in :func:`ellipsoid_h`.
    """
    ops, batch_shape, (x, c, a), rows = _prepare(x, None, center, axes, rotation)
    g, r2, _ = _barrier_terms(x, c, a, rows)
    n, _, _ = _inward_normal(ops, g, r2)
    out = np.empty((batch_shape or ()) + (3,))
    out[..., 0], out[..., 1], out[..., 2] = n
    return out


def filter_velocity(x, v_nominal, center, axes, alpha: float, rotation=None) -> CBFResult:
    """The paper's continuous-time closed form: v_s = v_n + max(-n . v_n - alpha h, 0) n.

    ``v_s`` is the minimum-norm change of ``v_n`` with ``n . v_s >= -alpha h(x)``. It is defined outside
    the set too (it then pushes inward at ``alpha |h|`` m/s). It does not account for holding ``v_s``
    over a control step; for that use :func:`filter_velocity_discrete`.

    Args:
        x: (3,) or (..., 3) needle-tip position (m), world frame.
        v_nominal: (3,) or (..., 3) nominal tip velocity (m/s), world frame.
        center, axes, rotation: the ellipsoid, as in :func:`ellipsoid_h`.
        alpha: class-K gain (> 0), 1/s in the paper's units (see the module docstring).

    Returns:
        :class:`CBFResult` (``step_scale`` is all ones).

    Raises:
        ValueError: for non-positive ``alpha`` or ``axes``, or a wrong shape.
    """
    alpha = _check_positive("alpha", alpha)
    ops, batch_shape, (x, c, a, v), rows = _prepare(x, v_nominal, center, axes, rotation)
    out = _continuous(ops, x, v, c, a, rows, alpha)
    return _result(batch_shape, *out)


def margin_level(margin: float, axes):
    """Barrier level h_m = 1 - (1 - margin / min(axes))^2 of the set tightened by ``margin`` metres.

    Every point within ``margin`` metres of {h >= h_m} lies in {h >= 0}.

    Args:
        margin: tracking-error allowance (m), 0 <= margin < min(axes).
        axes: (3,) or (..., 3) semi-axes (m).

    Returns:
        (...,) float64 in [0, 1) (a float for (3,) axes).
    """
    ops, _, (_, _, a), _ = _prepare(_ORIGIN, None, _ORIGIN, axes, None, margin=float(margin))
    return _margin_level(ops, float(margin), a)


def filter_velocity_discrete(
    x, v_nominal, center, axes, alpha: float, dt: float, margin: float = 0.0, rotation=None
) -> CBFResult:
    """Safe velocity to hold for a whole control step: h >= 0 along the step, not only at its start.

    Enforces h~(x + v_s dt) >= (1 - gamma) h~(x) with h~ = h - :func:`margin_level`, gamma =
    min(alpha dt, 1), by the paper's closed form on the linearized condition followed by an exact
    step-length limit (see the module docstring for the math and why it is sufficient).

    Args:
        x: (3,) or (..., 3) needle-tip position at the start of the step (m), world frame.
        v_nominal: (3,) or (..., 3) nominal tip velocity (m/s), world frame.
        center, axes, rotation: the ellipsoid, as in :func:`ellipsoid_h`.
        alpha: decay rate of the tightened barrier (1/s, > 0).
        dt: control period over which ``v_safe`` is held (s, > 0).
        margin: tracking-error allowance (m), 0 <= margin < min(axes).

    Returns:
        :class:`CBFResult`; ``h`` is the untightened barrier at ``x``.

    Raises:
        ValueError: for non-positive ``alpha``, ``dt`` or ``axes``, a ``margin`` outside
            [0, min(axes)), or a wrong shape.
    """
    alpha = _check_positive("alpha", alpha)
    dt = _check_positive("dt", dt)
    margin = float(margin)
    ops, batch_shape, (x, c, a, v), rows = _prepare(x, v_nominal, center, axes, rotation, margin=margin)
    out = _discrete(ops, x, v, c, a, rows, alpha, dt, margin)
    return _result(batch_shape, *out)


def suture_ellipsoid_frame(entry_point, exit_point, surface_normal) -> tuple[np.ndarray, np.ndarray]:
    """Centre and orientation of the safe ellipsoid for one suture throw.

    The centre is midway between the entry and exit points; the ellipsoid's axes are (entry->exit
    projected onto the tissue surface, lateral = normal x along, surface normal).

    Args:
        entry_point: (3,) world (m).
        exit_point: (3,) world (m).
        surface_normal: (3,) tissue surface normal pointing out of the tissue (any length > 0).

    Returns:
        (center (3,) m, rotation (3, 3) world-from-ellipsoid with columns along, lateral, normal).

    Raises:
        ValueError: if the entry->exit line has no component along the surface (points coincide, or
            the line is along the normal).
    """
    entry_point = np.asarray(entry_point, dtype=np.float64)
    exit_point = np.asarray(exit_point, dtype=np.float64)
    normal = np.asarray(surface_normal, dtype=np.float64)
    normal = normal / np.linalg.norm(normal)
    chord = exit_point - entry_point
    along = chord - (chord @ normal) * normal
    length = float(np.linalg.norm(along))
    if length < 1e-9:
        raise ValueError(
            "`entry_point` and `exit_point` must be apart along the tissue surface. "
            f"Got entry {entry_point.tolist()}, exit {exit_point.tolist()}."
        )
    along = along / length
    lateral = np.cross(normal, along)
    return 0.5 * (entry_point + exit_point), np.column_stack([along, lateral, normal])
