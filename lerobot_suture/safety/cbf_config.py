"""Configuration of the CBF safety filter: the safe ellipsoid's size, the barrier rate, the tracking
margin and the choice of filter, validated at construction. The math is :mod:`lerobot_suture.safety.cbf`."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lerobot_suture.safety.cbf import CBFResult, filter_velocity, filter_velocity_discrete, margin_level


@dataclass
class CBFConfig:
    """Configuration of the safety filter applied to the needle tip's velocity (draccus-compatible).

    Defaults: the safe ellipsoid has semi-axes 16 x 8 x 10 mm around the midpoint of an 18 mm
    entry-exit pair. A nominal throw (10 mm needle radius, 5.6 mm deep, plane tilted 30 degrees, tip
    protruding 5 mm past the exit point) reaches a scaled radius of about 0.81, inside the set
    tightened by the default 1 mm margin (scale 0.875); see ``tests/test_cbf.py``.

    Args:
        enabled: Apply the filter. When False, :class:`~lerobot_suture.safety.cbf_wrapper.CBFActionWrapper`
            only monitors (reports ``h`` and the activation state) and passes velocities through.
        alpha: Barrier rate (1/s, > 0). With ``discrete`` the tightened barrier may decay by at most a
            factor ``1 - alpha * control_dt`` per control step; without it this is the paper's alpha.
        semi_axis_along: Semi-axis (m, > 0) along the entry->exit line.
        semi_axis_lateral: Semi-axis (m, > 0) across the wound, in the tissue surface.
        semi_axis_normal: Semi-axis (m, > 0) along the tissue surface normal.
        margin: Tracking-error allowance (m), in [0, min semi-axis): the commanded tip stays this far
            inside the ellipsoid (discrete mode only; activation also waits until the tip is this far in).
        tissue_speed_max: Declared bound on the wound's speed (m/s, >= 0): faster motion is outside the
            filter's premises and is reported (``motion_exceeded``) so that control can be handed over.
        tissue_acceleration_max: Declared bound on the wound's acceleration (m/s^2, >= 0). The filter moves
            the tip relative to the wound's measured velocity and tightens the set by a further
            ``tissue_acceleration_max * control_dt^2``, how far the wound can stray within a step from where
            that velocity carries it; harder acceleration is reported as for the speed.
        discrete: Enforce the discrete-time condition with the step-length limit
            (:func:`filter_velocity_discrete`, keeps h >= 0 at every physics step). False applies the
            paper's continuous-time closed form only (:func:`filter_velocity`), for comparison: held
            for a 0.1 s step it can leave the set, and once outside its inward push of ``alpha |h|`` m/s
            ignores the step length and can overshoot.
    """

    # Switch.
    enabled: bool = False
    # Barrier.
    alpha: float = 5.0
    semi_axis_along: float = 0.016
    semi_axis_lateral: float = 0.008
    semi_axis_normal: float = 0.010
    # Discrete-time enforcement.
    margin: float = 0.001
    # Tissue motion.
    tissue_speed_max: float = 0.015
    tissue_acceleration_max: float = 0.02
    discrete: bool = True

    def __post_init__(self):
        if not isinstance(self.enabled, bool):
            raise ValueError(f"`enabled` must be a bool. Got {self.enabled!r}.")
        if not isinstance(self.discrete, bool):
            raise ValueError(f"`discrete` must be a bool. Got {self.discrete!r}.")
        names = ("alpha", "semi_axis_along", "semi_axis_lateral", "semi_axis_normal", "margin")
        for name in (*names, "tissue_speed_max", "tissue_acceleration_max"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
                raise ValueError(f"`{name}` must be a finite number. Got {value!r}.")
        for name in ("alpha", "semi_axis_along", "semi_axis_lateral", "semi_axis_normal"):
            value = getattr(self, name)
            if not value > 0:
                raise ValueError(f"`{name}` must be > 0. Got {value}.")
        for name in ("tissue_speed_max", "tissue_acceleration_max"):
            if getattr(self, name) < 0:
                raise ValueError(f"`{name}` must be >= 0. Got {getattr(self, name)}.")
        smallest = min(self.semi_axis_along, self.semi_axis_lateral, self.semi_axis_normal)
        if not 0 <= self.margin < smallest:
            raise ValueError(
                f"`margin` must be in [0, {smallest}) m (the smallest semi-axis). Got {self.margin}."
            )

    @property
    def semi_axes(self) -> np.ndarray:
        """(3,) semi-axes (m): along, lateral, normal."""
        return np.array([self.semi_axis_along, self.semi_axis_lateral, self.semi_axis_normal])

    @property
    def margin_level(self) -> float:
        """Barrier level of the tightened set, :func:`margin_level` (unit-free)."""
        return float(margin_level(self.margin, self.semi_axes))

    def filter(self, x, v_nominal, center, rotation, dt: float, margin: float | None = None) -> CBFResult:
        """Apply the configured filter (discrete or continuous) on the configured ellipsoid.

        Args:
            x: (3,) or (..., 3) tip position (m). v_nominal: same shape, m/s.
            center: (3,) ellipsoid centre (m). rotation: (3, 3) world-from-ellipsoid or None.
            dt: control period (s), used in discrete mode.
            margin: the tightening (m) in discrete mode; None: ``margin``.
        """
        if self.discrete:
            margin = self.margin if margin is None else margin
            return filter_velocity_discrete(
                x, v_nominal, center, self.semi_axes, self.alpha, dt, margin, rotation
            )
        return filter_velocity(x, v_nominal, center, self.semi_axes, self.alpha, rotation)
