"""The paper's experiment 4 offline: filter a recorded needle-tip trajectory and plot it.

A reference trajectory (recorded from the env, or a policy's unsafe prediction) is replayed through
the CBF. At each control step the nominal velocity is the one that reaches the next reference point
in one step, ``v_d = (p_ref[k+1] - x_k) / dt`` (a position-servoing command, so the safe trajectory
follows the reference wherever that is safe); once the tip is inside the set (the throw has begun)
the filter turns it into ``v_s``. The robot is modelled as the velocity tracking controller the
model-free CBF assumes: first order with rate ``tracking_rate`` (1/s, the theorem's lambda > alpha),
integrated exactly over ``substeps`` per control step. ``tracking_rate=None`` tracks perfectly.

The figure has the paper's layout: left, the 3D reference (red) and safe (blue) trajectories with the
ellipsoid (green wireframe); middle, h(x) over time for both with h = 0 marked; right, the desired,
safe and actual (current) speeds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from lerobot_suture.plotting import save_figure
from lerobot_suture.safety.cbf import ellipsoid_h, filter_velocity, filter_velocity_discrete, margin_level

_H_PLOT_FLOOR = -2.0
"""Lower limit of the h axis in the figure."""


@dataclass(frozen=True)
class CBFReplay:
    """A replayed trajectory. T control steps of ``dt`` seconds, K = (T - 1) * substeps + 1 fine samples.

    Attributes:
        dt: control period (s).
        time: (T,) control-step times (s).
        reference: (T, 3) reference tip positions (m).
        h_reference: (T,) barrier along the reference.
        v_desired: (T - 1, 3) nominal velocity per step (m/s).
        v_safe: (T - 1, 3) velocity sent to the robot per step (m/s).
        active: (T - 1,) bool, the filter was on.
        intervened: (T - 1,) bool, the filter changed the velocity.
        time_fine: (K,) fine times (s).
        actual: (K, 3) tip positions of the tracked (safe) trajectory (m).
        v_actual: (K, 3) its velocity (m/s).
        h_actual: (K,) barrier along it.
        h_margin: barrier level of the tightened set (0 without a margin).
    """

    dt: float
    time: np.ndarray
    reference: np.ndarray
    h_reference: np.ndarray
    v_desired: np.ndarray
    v_safe: np.ndarray
    active: np.ndarray
    intervened: np.ndarray
    time_fine: np.ndarray
    actual: np.ndarray
    v_actual: np.ndarray
    h_actual: np.ndarray
    h_margin: float

    @property
    def substeps(self) -> int:
        return (len(self.time_fine) - 1) // max(len(self.time) - 1, 1)

    @property
    def activation_index(self) -> int | None:
        """First control step with the filter on, or None."""
        idx = np.flatnonzero(self.active)
        return int(idx[0]) if idx.size else None


def replay_cbf(
    reference_tip_positions,
    dt: float,
    center,
    axes,
    rotation=None,
    alpha: float = 5.0,
    *,
    margin: float = 0.001,
    discrete: bool = True,
    tracking_rate: float | None = 50.0,
    substeps: int = 50,
) -> CBFReplay:
    """Filter a reference trajectory through the CBF, integrating from its first point.

    Args:
        reference_tip_positions: (T, 3) reference needle-tip positions (m), T >= 2, one per step.
        dt: control period (s, > 0).
        center: (3,) ellipsoid centre (m). axes: (3,) semi-axes (m). rotation: (3, 3) or None.
        alpha: barrier rate (1/s), as in :class:`~lerobot_suture.safety.cbf_config.CBFConfig`.
        margin: tracking-error allowance (m), discrete mode only.
        discrete: use :func:`filter_velocity_discrete` (True) or the paper's :func:`filter_velocity`.
        tracking_rate: first-order velocity tracking rate (1/s, > 0), or None for perfect tracking.
        substeps: fine samples per control step (>= 1), e.g. control_dt / physics_dt.

    Returns:
        :class:`CBFReplay`.

    Raises:
        ValueError: for a malformed reference or a non-positive ``dt``, ``tracking_rate`` or ``substeps``.
    """
    reference = np.asarray(reference_tip_positions, dtype=np.float64)
    if reference.ndim != 2 or reference.shape[1] != 3 or len(reference) < 2:
        raise ValueError(f"`reference_tip_positions` must have shape (T >= 2, 3). Got {reference.shape}.")
    if not np.isfinite(reference).all():
        raise ValueError("`reference_tip_positions` must be finite.")
    if not dt > 0:
        raise ValueError(f"`dt` must be > 0. Got {dt}.")
    if tracking_rate is not None and not tracking_rate > 0:
        raise ValueError(f"`tracking_rate` must be > 0 or None. Got {tracking_rate}.")
    if int(substeps) != substeps or substeps < 1:
        raise ValueError(f"`substeps` must be an integer >= 1. Got {substeps}.")
    center = np.asarray(center, dtype=np.float64)
    axes = np.asarray(axes, dtype=np.float64)
    h_margin = float(margin_level(margin, axes)) if discrete else 0.0
    n_steps = len(reference) - 1
    tau = dt * np.arange(1, substeps + 1) / substeps  # (S,) s
    if tracking_rate is None:
        decay = np.zeros_like(tau)
        lag = np.zeros_like(tau)
    else:
        decay = np.exp(-tracking_rate * tau)  # (S,)
        lag = (1.0 - decay) / tracking_rate  # (S,) s

    v_desired = np.empty((n_steps, 3))
    v_safe = np.empty((n_steps, 3))
    active = np.zeros(n_steps, dtype=bool)
    intervened = np.zeros(n_steps, dtype=bool)
    actual = [reference[:1].copy()]
    v_actual = [np.zeros((1, 3))]
    x, v_now, on = reference[0].copy(), np.zeros(3), False
    for k in range(n_steps):
        v_d = (reference[k + 1] - x) / dt
        on = on or ellipsoid_h(x, center, axes, rotation) >= h_margin
        if on and discrete:
            result = filter_velocity_discrete(x, v_d, center, axes, alpha, dt, margin, rotation)
        elif on:
            result = filter_velocity(x, v_d, center, axes, alpha, rotation)
        v_s = result.v_safe if on else v_d
        v_desired[k], v_safe[k], active[k] = v_d, v_s, on
        intervened[k] = on and result.intervened
        # First-order tracking of v_s, exact over the step: v(t) = v_s + (v0 - v_s) e^{-lambda t}.
        v_fine = v_s + (v_now - v_s) * decay[:, None]  # (S, 3)
        x_fine = x + v_s * tau[:, None] + (v_now - v_s) * lag[:, None]  # (S, 3)
        if tracking_rate is None:
            v_fine = np.broadcast_to(v_s, x_fine.shape).copy()
        actual.append(x_fine)
        v_actual.append(v_fine)
        x, v_now = x_fine[-1].copy(), v_fine[-1].copy()

    actual_arr = np.concatenate(actual)
    v_actual_arr = np.concatenate(v_actual)
    v_actual_arr[0] = v_actual_arr[1] if tracking_rate is None else 0.0
    return CBFReplay(
        dt=float(dt),
        time=dt * np.arange(n_steps + 1),
        reference=reference,
        h_reference=ellipsoid_h(reference, center, axes, rotation),
        v_desired=v_desired,
        v_safe=v_safe,
        active=active,
        intervened=intervened,
        time_fine=dt * np.arange(n_steps * substeps + 1) / substeps,
        actual=actual_arr,
        v_actual=v_actual_arr,
        h_actual=ellipsoid_h(actual_arr, center, axes, rotation),
        h_margin=h_margin,
    )


def replay_metrics(replay: CBFReplay) -> dict:
    """Summary of a replay, JSON-serializable.

    Barrier minima are taken from the activation step on (before it, the tip has not entered the set
    and the filter is off); they are None when the filter never switched on.
    """
    k0 = replay.activation_index
    if k0 is None:
        h_min_ref = h_min_safe = None
    else:
        h_min_ref = float(replay.h_reference[k0:].min())
        h_min_safe = float(replay.h_actual[k0 * replay.substeps :].min())
    at_steps = replay.actual[:: replay.substeps]
    deviation = np.linalg.norm(at_steps - replay.reference, axis=1)
    return {
        "steps": int(len(replay.time) - 1),
        "dt_s": replay.dt,
        "activation_time_s": None if k0 is None else float(replay.time[k0]),
        "steps_active": int(replay.active.sum()),
        "steps_intervened": int(replay.intervened.sum()),
        "h_min_reference": h_min_ref,
        "h_min_safe": h_min_safe,
        "left_set_reference": None if h_min_ref is None else h_min_ref < 0.0,
        "left_set_safe": None if h_min_safe is None else h_min_safe < 0.0,
        "max_deviation_m": float(deviation.max()),
        "max_speed_desired_m_s": float(np.linalg.norm(replay.v_desired, axis=1).max()),
        "max_speed_safe_m_s": float(np.linalg.norm(replay.v_safe, axis=1).max()),
    }


def ellipsoid_wireframe(center, axes, rotation=None, n_u: int = 24, n_v: int = 12):
    """Surface grid of the ellipsoid for plotting: three (n_v, n_u) arrays X, Y, Z (m, world)."""
    u = np.linspace(0.0, 2.0 * math.pi, n_u)
    v = np.linspace(0.0, math.pi, n_v)
    local = np.stack(
        [
            axes[0] * np.outer(np.sin(v), np.cos(u)),
            axes[1] * np.outer(np.sin(v), np.sin(u)),
            axes[2] * np.outer(np.cos(v), np.ones_like(u)),
        ],
        axis=-1,
    )  # (n_v, n_u, 3)
    world = local if rotation is None else local @ np.asarray(rotation, dtype=np.float64).T
    world = world + np.asarray(center, dtype=np.float64)
    return world[..., 0], world[..., 1], world[..., 2]


def plot_replay(replay: CBFReplay, center, axes, rotation, out_path, title: str | None = None) -> Path:
    """Write the paper's three-panel figure (PNG) for a replay. Positions in mm, speeds in mm/s.

    Args:
        replay: from :func:`replay_cbf`.
        center, axes, rotation: the ellipsoid used for the replay.
        out_path: PNG path; parent folders are created.
        title: optional figure title.

    Returns:
        The path written.
    """
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    fig = Figure(figsize=(16, 4.8), layout="constrained")
    FigureCanvasAgg(fig)
    mm = 1000.0

    ax3d = fig.add_subplot(1, 3, 1, projection="3d")
    ex, ey, ez = ellipsoid_wireframe(center, axes, rotation)
    ax3d.plot_wireframe(ex * mm, ey * mm, ez * mm, color="green", linewidth=0.5, alpha=0.5, label="safe set")
    ref, act = replay.reference * mm, replay.actual * mm
    ax3d.plot(ref[:, 0], ref[:, 1], ref[:, 2], color="red", linewidth=1.5, label="reference")
    ax3d.plot(act[:, 0], act[:, 1], act[:, 2], color="blue", linewidth=1.5, label="safe (CBF)")
    ax3d.scatter(*ref[0], color="black", s=15, label="start")
    span = np.concatenate([ref, act, np.stack([ex, ey, ez], -1).reshape(-1, 3) * mm])
    ax3d.set_box_aspect(np.maximum(np.ptp(span, axis=0), 1e-6), zoom=0.85)
    ax3d.set_xlabel("x (mm)")
    ax3d.set_ylabel("y (mm)")
    ax3d.set_zlabel("z (mm)")
    ax3d.set_title("Needle-tip trajectory")
    ax3d.legend(loc="upper left", fontsize="small")

    ax_h = fig.add_subplot(1, 3, 2)
    ax_h.plot(replay.time, replay.h_reference, color="red", marker=".", markersize=3, label="reference")
    ax_h.plot(replay.time_fine, replay.h_actual, color="blue", label="safe (CBF)")
    ax_h.axhline(0.0, color="black", linestyle="--", linewidth=1, label="h = 0 (boundary)")
    if replay.h_margin > 0:
        ax_h.axhline(replay.h_margin, color="grey", linestyle=":", linewidth=1, label="margin")
    k0 = replay.activation_index
    if k0 is not None:
        ax_h.axvline(replay.time[k0], color="green", linestyle=":", linewidth=1, label="CBF on")
    h_floor = min(float(replay.h_reference.min()), float(np.nanmin(replay.h_actual)))
    if h_floor < _H_PLOT_FLOOR:  # far outside the set h is very negative; keep the boundary readable
        ax_h.set_ylim(_H_PLOT_FLOOR, 1.05)
        ax_h.text(0.01, 0.01, f"clipped below {_H_PLOT_FLOOR:g}", transform=ax_h.transAxes, fontsize="small")
    ax_h.set_xlabel("time (s)")
    ax_h.set_ylabel("h(x)")
    ax_h.set_title("Barrier function")
    ax_h.legend(fontsize="small")
    ax_h.grid(alpha=0.3)

    ax_v = fig.add_subplot(1, 3, 3)
    t_steps = replay.time
    for vel, color, label in (
        (replay.v_desired, "red", "desired $V_d$"),
        (replay.v_safe, "blue", "safe $V_s$"),
    ):
        speed = np.linalg.norm(vel, axis=1) * mm
        ax_v.step(t_steps, np.append(speed, speed[-1]), where="post", color=color, label=label)
    ax_v.plot(
        replay.time_fine,
        np.linalg.norm(replay.v_actual, axis=1) * mm,
        color="orange",
        label="actual $V_{curr}$",
    )
    ax_v.set_xlabel("time (s)")
    ax_v.set_ylabel("speed (mm/s)")
    ax_v.set_title("Velocity")
    ax_v.legend(fontsize="small")
    ax_v.grid(alpha=0.3)

    if title:
        fig.suptitle(title)
    save_figure(fig, out_path, dpi=110)
    return out_path


def replay_and_plot(
    reference_tip_positions,
    dt: float,
    center,
    axes,
    rotation,
    alpha: float,
    out_path,
    *,
    margin: float = 0.001,
    discrete: bool = True,
    tracking_rate: float | None = 50.0,
    substeps: int = 50,
    title: str | None = None,
) -> dict:
    """Replay a reference trajectory through the CBF, write the three-panel PNG, return metrics.

    Args:
        reference_tip_positions: (T, 3) reference needle-tip positions (m).
        dt: control period (s).
        center, axes, rotation: the ellipsoid (m; rotation (3, 3) world-from-ellipsoid or None).
        alpha: barrier rate (1/s).
        out_path: PNG path.
        margin, discrete, tracking_rate, substeps: see :func:`replay_cbf`.
        title: optional figure title.

    Returns:
        :func:`replay_metrics` plus ``"out_path"`` (str).
    """
    replay = replay_cbf(
        reference_tip_positions,
        dt,
        center,
        axes,
        rotation,
        alpha,
        margin=margin,
        discrete=discrete,
        tracking_rate=tracking_rate,
        substeps=substeps,
    )
    path = plot_replay(replay, center, axes, rotation, out_path, title=title)
    return {**replay_metrics(replay), "out_path": str(path)}
