"""Figures of the paper's experiments (matplotlib, Agg, PNG)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from lerobot_suture.plotting import save_figure

ID_COLOUR = "#c8ecc8"
OOD_COLOUR = "#f6c4c4"
SCORE_LABELS = {
    "max_abs_cov": r"uncertainty $\hat\sigma$ = max $|\Sigma_t|$",
    "trace": r"uncertainty max$_t$ tr $\Sigma_t$",
    "logdet": r"uncertainty max$_t$ log det $\Sigma_t$",
}
"""The y-axis label of each uncertainty score (the policy's ``uncertainty_score``)."""


def _padded(runs: Sequence[Sequence[float]]) -> np.ndarray:
    """Runs of unequal length as one (R, T) array, NaN-padded."""
    length = max((len(r) for r in runs), default=0)
    out = np.full((len(runs), length), np.nan)
    for i, r in enumerate(runs):
        out[i, : len(r)] = r
    return out


def plot_uncertainty(
    scenario_runs: Sequence[Sequence[float]],
    threshold: float,
    out_path: str | Path,
    title: str,
    onset_steps: Sequence[int | None] = (),
    nominal_runs: Sequence[Sequence[float]] = (),
    score_name: str = "max_abs_cov",
) -> Path:
    """The paper's uncertainty figure: the score per timestep, the maximum over runs in bold and each run
    faint, the background green where the gate says I.D. (max below the threshold) and red where O.O.D.,
    the perturbation onset marked; nominal runs (grey) beside them for reference. ``score_name`` (a key of
    :data:`SCORE_LABELS`) labels the y axis.
    """
    scores = _padded(scenario_runs)
    fig = Figure(figsize=(9, 3.6), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    if scores.size:
        with np.errstate(all="ignore"):
            max_run = np.nanmax(np.where(np.isnan(scores), -np.inf, scores), axis=0)
        steps = np.arange(scores.shape[1])
        if math.isfinite(threshold):
            ood = max_run > threshold
            for k in steps:
                ax.axvspan(k - 0.5, k + 0.5, color=OOD_COLOUR if ood[k] else ID_COLOUR, lw=0)
        for nominal in nominal_runs:
            ax.plot(np.arange(len(nominal)), nominal, color="0.55", lw=0.6, alpha=0.5)
        for run in scores:
            ax.plot(steps, run, color="tab:blue", lw=0.7, alpha=0.35)
        ax.plot(steps, max_run, color="navy", lw=1.8, label=f"max over {len(scenario_runs)} runs")
        if nominal_runs:
            ax.plot([], [], color="0.55", lw=0.8, label=f"nominal runs ({len(nominal_runs)})")
    if math.isfinite(threshold):
        ax.axhline(threshold, color="darkred", ls="--", lw=1.0, label="gate threshold")
    onsets = [o for o in onset_steps if o is not None]
    if onsets:
        onset = int(np.median(onsets))
        ax.axvline(onset, color="black", ls=":", lw=1.4, label=f"perturbation onset (step {onset})")
    ax.set_xlabel("control step (10 Hz)")
    ax.set_ylabel(SCORE_LABELS[score_name])
    ax.set_title(title)
    ax.set_xlim(-0.5, max(scores.shape[1] - 0.5, 1))
    ax.legend(loc="upper left", fontsize=8, framealpha=0.9)
    fig.tight_layout()
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, out_path)
    return out_path
