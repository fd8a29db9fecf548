"""The leaderboard as a table and a figure: per task, each row's success under each condition with its 95%
interval, and what the gate and the CBF did."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from lerobot_suture.leaderboard.cells import (
    SHIFT_PREFIX,
    conditions,
    has_throws,
    row_summary,
    task_conditions,
    throws_on_marks_mean,
)
from lerobot_suture.plotting import save_figure

BOARD_DPI = 90
"""Resolution of ``leaderboard.png`` (dots per inch): readable, and small enough for the results' size budget."""


def _percent(x: float) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.0f}"


def render(board: dict) -> str:
    """The leaderboard as markdown: per task, success % [95% interval] of each policy under each condition,
    then the gate's and the CBF's rows."""
    lines = [
        "# Leaderboard",
        "",
        f"{board['episodes']} episodes a cell, the same test seeds for every policy; the CBF filters every "
        "action; gates report and never stop a run. Success % [95% Wilson interval]; `gate` is the share of "
        "episodes the policy's O.O.D. gate flagged (false alarms on nominal); `CBF` is the share of its "
        "active steps the filter changed and the episodes that left the safe set. The summary is over the "
        "board's conditions; a condition some rows lack (a joining row's further shifts) is a line of the "
        "second table only.",
        "",
    ]
    for task, rows in board["tasks"].items():
        policies = list(rows)
        conds = task_conditions(rows)
        board_conds = conditions(task, board.get("shifts", []))
        summaries = {policy: row_summary(rows[policy], board_conds) for policy in policies}
        # A suture of several throws: how far into it the policies get, beside success.
        throws = has_throws(rows)
        lines += [
            f"## {task}",
            "",
            "| policy | nominal success | mean over the scenarios | mean over the shifts | gate false alarms "
            "| episodes out of the safe set |"
            + (" throws on the marks a nominal episode, mean |" if throws else ""),
            "|---|---|---|---|---|---|" + ("---|" if throws else ""),
        ]
        for policy, s in summaries.items():
            line = (
                f"| {policy} | {_percent(s['nominal_success'])} | {_percent(s['scenario_success_mean'])} | "
                f"{_percent(s['shift_success_mean'])} | {_percent(s['nominal_false_alarms'])} | "
                f"{s['cbf_violating_episodes']} of {s['episodes']} |"
            )
            if throws:
                mean = s["nominal_throws_on_marks"]
                line += " n/a |" if mean is None else f" {mean:.2f} |"
            lines.append(line)
        lines += ["", "| condition | " + " | ".join(policies) + " |"]
        lines.append("|---|" + "---|" * len(policies))
        for cond in conds:
            cells = []
            for policy in policies:
                cell = rows[policy].get(cond)
                if cell is None:
                    cells.append("-")
                    continue
                low, high = cell["success_interval"]
                text = f"{_percent(cell['success_rate'])} [{_percent(low)}, {_percent(high)}]"
                if cell["gate"] is not None:
                    text += f", gate {_percent(cell['gate']['flagged_rate'])}"
                cbf = cell["cbf"]
                text += f", CBF {_percent(cbf['intervention_rate'])} / {cbf['violating_episodes']}"
                mean_throws = throws_on_marks_mean(cell)
                if mean_throws is not None:
                    text += f", throws {mean_throws:.2f}"
                cells.append(text)
            lines.append(f"| {cond} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += _seed_lines(board)
    if board.get("timings"):
        lines += ["## Time", "", "| stage | seconds |", "|---|---|"]
        lines += [f"| {k} | {v:.0f} |" for k, v in board["timings"].items()]
        lines.append("")
    return "\n".join(lines)


def _seed_lines(board: dict) -> list[str]:
    """Per task, each seeded row's success over its training seeds: the mean with the range over the seeds,
    then each seed's rate with its Wilson interval."""
    lines = []
    for task, policies in board.get("seed_spread", {}).items():
        lines += [
            f"## {task}: training seeds",
            "",
            "Success % over the training seeds: mean [lowest, highest seed], then each seed's rate [95% Wilson "
            "interval]. The further seeds run nominal and the scenarios only.",
            "",
            "| policy | condition | mean [range] over seeds | per seed |",
            "|---|---|---|---|",
        ]
        for policy, by_condition in policies.items():
            for condition, spread in by_condition.items():
                low, high = spread["success_range"]
                per_seed = "; ".join(
                    f"{seed}: {_percent(s['success_rate'])} [{_percent(s['success_interval'][0])}, "
                    f"{_percent(s['success_interval'][1])}]"
                    for seed, s in spread["per_seed"].items()
                )
                lines.append(
                    f"| {policy} | {condition} | {_percent(spread['success_mean'])} [{_percent(low)}, "
                    f"{_percent(high)}] | {per_seed} |"
                )
        lines.append("")
    return lines


def _bars(ax, rows: dict, conds: list[str], colour: dict, value, interval=None) -> None:
    """One bar per policy and condition: ``value(cell)``, with ``interval(cell)`` as error bars if given."""
    policies = list(rows)
    width = 0.8 / max(1, len(policies))
    for j, policy in enumerate(policies):
        x = np.arange(len(conds)) + (j - (len(policies) - 1) / 2) * width
        cells = [rows[policy].get(c) for c in conds]
        height = np.array([value(c) if c else np.nan for c in cells], dtype=float)
        ax.bar(x, height, width, label=policy, color=colour[policy])
        if interval is not None:
            low, high = np.array([interval(c) if c else (np.nan, np.nan) for c in cells], dtype=float).T
            # Clipped: at a rate of 0 or 1 the interval's end can miss the rate by a rounding error.
            yerr = np.clip([height - low, high - height], 0, None)
            ax.errorbar(x, height, yerr=yerr, fmt="none", ecolor="black", capsize=2, lw=0.8)
    ax.set_xticks(np.arange(len(conds)))
    ax.set_xticklabels([c.removeprefix(SHIFT_PREFIX) for c in conds], rotation=35, ha="right", fontsize=8)
    ax.legend(fontsize=8, ncol=len(policies))


def plot(board: dict, path: Path) -> Path:
    """Success rate with its 95% interval, per condition, one bar per policy; one panel per task, and for a
    task of several throws a second panel of the throws on the marks per episode."""
    tasks = [t for t, rows in board["tasks"].items() if rows]
    panels = []
    for task in tasks:
        panels.append((task, "success"))
        if has_throws(board["tasks"][task]):
            panels.append((task, "throws"))
    most = max((len(task_conditions(board["tasks"][t])) for t in tasks), default=0)
    fig = Figure(figsize=(max(12, 0.7 * most), 3.2 * max(1, len(panels))), constrained_layout=True)
    FigureCanvasAgg(fig)
    # One colour per policy across the panels, in the order the policies first appear on the board.
    names = list(dict.fromkeys(name for t in tasks for name in board["tasks"][t]))
    palette = matplotlib.colormaps["tab10"]
    colour = {name: palette(i % palette.N) for i, name in enumerate(names)}
    for k, (task, panel) in enumerate(panels):
        ax = fig.add_subplot(len(panels), 1, k + 1)
        rows = board["tasks"][task]
        conds = task_conditions(rows)
        if panel == "success":
            _bars(ax, rows, conds, colour, lambda c: c["success_rate"], lambda c: c["success_interval"])
            ax.set_ylim(0, 1.2)  # room for the legend above the bars
            ax.set_ylabel("success rate")
            ax.set_title(f"{task}: {board['episodes']} episodes a cell, 95% Wilson intervals")
        else:
            tables = [c["per_throw"] for row in rows.values() for c in row.values() if "per_throw" in c]
            n_throws = max(len(table["throws"]) for table in tables)
            _bars(ax, rows, conds, colour, throws_on_marks_mean)  # None (no throws) draws no bar
            ax.set_ylim(0, 1.2 * n_throws)
            ax.set_ylabel("throws on the marks")
            ax.set_title(f"{task}: throws on the marks per episode, mean (of {n_throws})")
    path = Path(path)
    save_figure(fig, path, dpi=BOARD_DPI)
    return path
