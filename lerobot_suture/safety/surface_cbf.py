r"""The tissue surface as a barrier: the half-space above the tissue, and its discrete-time filter.

Pure numpy. The tissue surface is the plane through the wound's entry point with unit normal ``n`` (out of
the tissue). A point's height above it is ``z(x) = (x - entry) . n`` (m). The half-space tightened by a
margin ``m`` is ``{x : z(x) >= m}``; its barrier, in metres, is::

    g(x) = z(x) - m

Discrete-time condition, held for a control step ``dt`` (the same form as the ellipsoid's,
:func:`lerobot_suture.safety.cbf.filter_velocity_discrete`)::

    g(x + v dt) >= (1 - gamma) g(x),   gamma = min(alpha dt, 1)
    <=>  n . v >= -gamma g(x) / dt

``g`` is linear, so the condition is exact and its minimum-norm solution is the closed form
``v_s = v + max(-gamma g(x) / dt - n . v, 0) n``. Along the commanded segment ``g`` is linear too: it stays
``>= 0`` when ``g(x) >= 0``, and never falls below ``g(x)`` when ``g(x) < 0`` (the filter then lifts the tip
by at least ``gamma |g(x)|`` per step).
"""

from __future__ import annotations

import numpy as np


def surface_height(points, entry_point, surface_normal) -> np.ndarray:
    """Height (m) of ``points`` (..., 3) above the tissue plane through ``entry_point`` (3,) with unit
    ``surface_normal`` (3,): negative below the surface. (...,) float64."""
    return (np.asarray(points, dtype=np.float64) - entry_point) @ surface_normal


def filter_velocity_surface(
    x: np.ndarray,
    v_nominal: np.ndarray,
    entry_point: np.ndarray,
    surface_normal: np.ndarray,
    alpha: float,
    dt: float,
    margin: float,
) -> tuple[np.ndarray, bool]:
    """Minimum-norm change of ``v_nominal`` (3,) m/s that keeps the tip at ``x`` (3,) m above the tightened
    surface for a control step of ``dt`` s (see the module docstring).

    Args:
        entry_point: (3,) m, a point of the surface. surface_normal: (3,) unit normal out of the tissue.
        alpha: barrier rate (1/s, > 0). margin: height (m, >= 0) the tip is kept above the surface.

    Returns:
        (v_safe (3,) m/s, whether it differs from ``v_nominal``).
    """
    gamma = min(alpha * dt, 1.0)
    g = float(surface_height(x, entry_point, surface_normal)) - margin
    v = np.asarray(v_nominal, dtype=np.float64)
    correction = max(-gamma * g / dt - float(surface_normal @ v), 0.0)
    if correction == 0.0:
        return v.copy(), False
    return v + correction * surface_normal, True
