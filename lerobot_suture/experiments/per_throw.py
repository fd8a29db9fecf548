"""A running suture's outcome throw by throw, and what the O.O.D. gate and the CBF did on each throw.

Pure functions of :class:`~lerobot_suture.runtime.rollout.EpisodeLog` records: a throw ``k`` is *reached*
when the episode begins it (the first always; a later one once the one before was extracted), *on the
marks* when the env's record of it says its entry and exit were within 2 mm, *off the marks* when it
was driven through elsewhere (the episode ends there), and *unfinished* when the episode ran out of
steps before it was over. A step belongs to the throw the env reports after that step.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lerobot_suture.experiments.metrics import summarize, wilson_interval
from lerobot_suture.plotting import save_figure
from lerobot_suture.runtime.rollout import EpisodeLog, StepLog


def _rate(successes: int, n: int) -> dict:
    """A count out of ``n`` with its rate and 95% Wilson interval (None for both when ``n`` is 0)."""
    if n == 0:
        return {"count": successes, "of": 0, "rate": None, "wilson_95": None}
    return {
        "count": successes,
        "of": n,
        "rate": successes / n,
        "wilson_95": list(wilson_interval(successes, n)),
    }


def throw_steps(log: EpisodeLog, throw: int) -> list[StepLog]:
    """The steps of ``log`` that belong to throw ``throw`` (0-based)."""
    return [s for s in log.steps if s.throw_index == throw]


def throw_outcome(log: EpisodeLog, throw: int) -> str:
    """``not_reached``, ``on_marks``, ``off_marks`` or ``unfinished``: throw ``throw`` of the episode."""
    results = log.throw_results
    reached = throw == 0 or (len(results) >= throw and results[throw - 1].get("extracted", False))
    if not reached:
        return "not_reached"
    if len(results) <= throw:
        return "unfinished"
    return "on_marks" if results[throw]["on_marks"] else "off_marks"


def gate_on_throw(log: EpisodeLog, throw: int) -> dict:
    """The gate during throw ``throw``: whether it alarmed at any of its steps, and whether the episode's
    first alarm fell in it."""
    steps = throw_steps(log, throw)
    first = log.first_alarm_step
    return {
        "alarmed": any(s.ood for s in steps),
        "first_alarm_here": first is not None and log.steps[first].throw_index == throw,
    }


def cbf_on_throw(logs: Sequence[EpisodeLog], throw: int) -> dict:
    """The CBF over throw ``throw`` of every episode: steps it was active and filtering, the smallest barrier
    value at the physics rate (``cbf.ellipsoid_h``, dimensionless, >= 0 inside the safe set), and the
    control steps with a physics step at h < 0."""
    steps = [s for log in logs for s in throw_steps(log, throw)]
    active = [s for s in steps if s.cbf_active]
    h_physics = [s.h_min_physics for s in active if not math.isnan(s.h_min_physics)]
    return {
        "steps": len(steps),
        "active_steps": len(active),
        "interventions": int(sum(s.cbf_intervened for s in active)),
        "intervention_rate": float(np.mean([s.cbf_intervened for s in active])) if active else 0.0,
        "h_min_physics": float(min(h_physics)) if h_physics else None,
        "steps_with_violation": int(sum(h < 0 for h in h_physics)),
    }


def per_throw_table(logs: Sequence[EpisodeLog], n_throws: int) -> dict:
    """Every throw's outcome over ``logs`` (success among all episodes and among those that reached it, with
    95% Wilson intervals), its entry and exit errors, the gate and the CBF on it; and the whole suture."""
    n = len(logs)
    throws = []
    for k in range(n_throws):
        outcomes = [throw_outcome(log, k) for log in logs]
        reached = [log for log, o in zip(logs, outcomes, strict=True) if o != "not_reached"]
        over = [
            log.throw_results[k]
            for log, o in zip(logs, outcomes, strict=True)
            if o in ("on_marks", "off_marks")
        ]
        gates = [
            (gate_on_throw(log, k), o) for log, o in zip(logs, outcomes, strict=True) if o != "not_reached"
        ]
        failed = [g for g, o in gates if o != "on_marks"]
        succeeded = [g for g, o in gates if o == "on_marks"]
        on_marks = outcomes.count("on_marks")
        throws.append(
            {
                "throw": k + 1,
                "reached": len(reached),
                "on_marks": _rate(on_marks, n),
                "on_marks_when_reached": _rate(on_marks, len(reached)),
                "off_marks": outcomes.count("off_marks"),
                "unfinished": outcomes.count("unfinished"),
                "extracted": int(sum(r.get("extracted", False) for r in over)),
                "entry_error_mm": summarize([1000 * r["entry_error_m"] for r in over]),
                "exit_error_mm": summarize([1000 * r["exit_error_m"] for r in over]),
                "gate": {
                    "first_alarm_here": int(sum(g["first_alarm_here"] for g, _ in gates)),
                    "alarmed_on_failed_throw": _rate(sum(g["alarmed"] for g in failed), len(failed)),
                    "alarmed_on_throw_on_marks": _rate(sum(g["alarmed"] for g in succeeded), len(succeeded)),
                },
                "cbf": cbf_on_throw(logs, k),
            }
        )
    return {
        "episodes": n,
        "throws": throws,
        "all_throws_on_marks": _rate(int(sum(log.success for log in logs)), n),
        "throws_on_marks_per_episode": summarize(
            [sum(r["on_marks"] for r in log.throw_results) for log in logs]
        ),
        "episodes_with_an_alarm": int(sum(log.first_alarm_step is not None for log in logs)),
    }


def _throw_axes(ax, n_throws: int, ylabel: str) -> None:
    """A panel of shares (0 to 1) over throws 1..n_throws, with its legend."""
    ax.set(
        xticks=np.arange(1, n_throws + 1),
        xlim=(0.4, n_throws + 0.6),
        xlabel="throw",
        ylabel=ylabel,
        ylim=(0, 1.05),
    )
    ax.legend(fontsize=8)


def plot_per_throw(table: dict, out_path: str | Path, title: str) -> Path:
    """Two panels of :func:`per_throw_table`'s result: each throw on the marks (of all episodes and of those
    that reached it, 95% Wilson bars), and the share of failed and of good throws the gate alarmed on."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    throws = table["throws"]
    x = np.arange(1, len(throws) + 1)
    fig = Figure(figsize=(9, 3.6))
    FigureCanvasAgg(fig)
    left, right = fig.subplots(1, 2)
    for offset, key, label in (
        (-0.2, "on_marks", "of all episodes"),
        (0.2, "on_marks_when_reached", "of those reaching it"),
    ):
        rates = np.array([t[key]["rate"] if t[key]["of"] else np.nan for t in throws], dtype=float)
        bounds = np.array([t[key]["wilson_95"] or (np.nan, np.nan) for t in throws], dtype=float)
        err = np.abs(bounds.T - rates)
        left.bar(x + offset, rates, 0.4, yerr=err, capsize=3, label=label)
    _throw_axes(left, len(throws), "on the marks (entry and exit within 2 mm)")
    for offset, key, label in (
        (-0.2, "alarmed_on_failed_throw", "failed or unfinished throws"),
        (0.2, "alarmed_on_throw_on_marks", "throws on the marks"),
    ):
        rates = np.array(
            [t["gate"][key]["rate"] if t["gate"][key]["of"] else np.nan for t in throws], dtype=float
        )
        right.bar(x + offset, rates, 0.4, label=label)
    _throw_axes(right, len(throws), "share with a gate alarm")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, out, dpi=120)
    return out


def _pct(rate: dict) -> str:
    if rate["rate"] is None:
        return "--"
    low, high = rate["wilson_95"]
    return f"{rate['count']} of {rate['of']}, {100 * rate['rate']:.0f}% [{100 * low:.1f}, {100 * high:.1f}]"


def _share(rate: dict) -> str:
    return "--" if rate["rate"] is None else f"{rate['count']} of {rate['of']}"


def per_throw_markdown(table: dict) -> str:
    """:func:`per_throw_table`'s result as a markdown table, a row per throw, and the whole suture below it."""
    lines = [
        "| throw | reached | on the marks, of all [95% Wilson] | of those reaching it | off the marks / "
        "unfinished | extracted | gate alarmed: on failed throws / on throws on the marks | CBF: active "
        "steps, interventions, min h at the physics rate |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for t in table["throws"]:
        cbf = t["cbf"]
        h = "--" if cbf["h_min_physics"] is None else f"{cbf['h_min_physics']:.3f}"
        lines.append(
            f"| {t['throw']} | {t['reached']} | {_pct(t['on_marks'])} | {_pct(t['on_marks_when_reached'])} | "
            f"{t['off_marks']} / {t['unfinished']} | {t['extracted']} | "
            f"{_share(t['gate']['alarmed_on_failed_throw'])} / {_share(t['gate']['alarmed_on_throw_on_marks'])} | "
            f"{cbf['active_steps']}, {cbf['interventions']}, {h} |"
        )
    lines += [
        "",
        f"All four throws on the marks: {_pct(table['all_throws_on_marks'])}. Episodes with a gate alarm: "
        f"{table['episodes_with_an_alarm']} of {table['episodes']}.",
    ]
    return "\n".join(lines) + "\n"
