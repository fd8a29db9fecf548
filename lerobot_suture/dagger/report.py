"""The loop's table (``dagger.md``, ``dagger.json``: a row per arm and round) and figure (``dagger.png``:
autonomy and success against the cumulative labelled frames, a panel per scenario, the arms side by side).
Autonomy comes with its Wilson interval and, from round 1, its paired change from round 0 on the same seeds.

Round 0 (the given policy) opens every arm's rows with no new frames. Rows of rounds not finished yet are
left out, so the table can be written from a run still under way.
"""

from __future__ import annotations

import math
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from lerobot_suture.dagger.config import ARMS, GATED, SCENARIOS
from lerobot_suture.datasets.metadata import read_json, write_json_atomic
from lerobot_suture.experiments import metrics
from lerobot_suture.plotting import save_figure
from lerobot_suture.runtime.takeover import GATE_RELEASED, TAKEN_OVER

SHORT = {
    "nominal": "nominal",
    "phantom_moved_after_insertion": "moved after insertion",
    "camera_moved": "camera moved",
    "phantom_servo": "phantom servo",
}
COLOURS = {"gated": "tab:red", "ungated": "tab:blue", "bc": "tab:green"}
MARKERS = {"gated": "o", "ungated": "s", "bc": "^"}


def table_rows(output_dir: Path, arms: list[str], rounds: int) -> list[dict]:
    """One row per arm and finished round, from the rounds' ``eval.json`` and ``collect.json``."""
    output_dir = Path(output_dir)
    round0 = output_dir / "round_0" / "eval.json"
    if not round0.is_file():
        return []
    baseline = read_json(round0)
    rows = []
    for arm in arms:
        cumulative = 0
        for round_ in range(rounds + 1):
            folder = output_dir / "round_0" if round_ == 0 else output_dir / arm / f"round_{round_}"
            if not (folder / "eval.json").is_file():
                break
            collect = {} if round_ == 0 else read_json(folder / "collect.json")
            new = int(collect.get("new_frames", 0))
            cumulative += new
            result = baseline if round_ == 0 else read_json(folder / "eval.json")
            rows.append(_row(arm, round_, new, cumulative, result))
            rows[-1].update(autonomy_statistics(result, baseline if round_ else None))
            rows[-1]["collection_handovers"] = handover_reasons(collect.get("runs", []))
    return rows


def autonomy_statistics(result: dict, round0: dict | None) -> dict:
    """Per scenario, autonomous success's 95% Wilson interval and, given round 0's evaluation, its change
    from round 0 on the same test seeds (:func:`~lerobot_suture.experiments.metrics.paired_change`); empty
    for an evaluation written before its episodes were kept."""
    if "episodes" not in result or (round0 is not None and "episodes" not in round0):
        return {}
    out = {"autonomous_interval": {}}
    for scenario, episodes in result["episodes"].items():
        after = [bool(e["autonomous_success"]) for e in episodes]
        out["autonomous_interval"][scenario] = list(metrics.wilson_interval(sum(after), len(after)))
        if round0 is not None:
            by_seed = {e["seed"]: bool(e["autonomous_success"]) for e in round0["episodes"][scenario]}
            paired = metrics.paired_change([by_seed[e["seed"]] for e in episodes], after)
            out.setdefault("autonomous_change", {})[scenario] = {
                **paired,
                "interval": list(paired["interval"]),
            }
    return out


def handover_reasons(runs: list[dict]) -> dict[str, int]:
    """Collection episodes by why control first changed hands (the gate released it, or the surgeon
    took it); runs written before the reason was kept count under "gate released"."""
    counts: dict[str, int] = {}
    for run in runs:
        if run.get("handover_step") is not None:
            reason = run.get("handover_reason") or GATE_RELEASED
            counts[reason] = counts.get(reason, 0) + 1
    return counts


def _row(arm: str, round_: int, new: int, cumulative: int, result: dict) -> dict:
    scenarios = result["scenarios"]
    overall = result["overall"]
    return {
        "arm": arm,
        "round": round_,
        "new_frames": new,
        "cumulative_frames": cumulative,
        "autonomous_success": {s: scenarios[s]["autonomous_success"] for s in scenarios},
        "success": {s: scenarios[s]["success"] for s in scenarios},
        "overall_autonomous_success": overall["autonomous_success"],
        "overall_success": overall["success"],
        "handovers_per_episode": overall["handovers_per_episode"],
        "surgeon_steps_per_episode": overall["surgeon_steps_per_episode"],
        "nominal_false_alarms_per_episode": result["nominal_false_alarms_per_episode"],
        "auroc": dict(result["auroc"]),
        "test_episodes_per_scenario": scenarios["nominal"]["episodes"],
        "threshold": result.get("threshold"),
    }


def _fmt(value, digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def markdown(rows: list[dict], toy: bool = False) -> str:
    perturbed = [s for s in SCENARIOS if s != "nominal"]
    header = (
        ["arm", "round", "new frames", "cumulative frames"]
        + [f"autonomous, {SHORT[s]}" for s in SCENARIOS]
        + [
            "autonomous, all",
            "success, all",
            "handovers / ep",
            "surgeon steps / ep",
            "nominal false alarms / ep",
        ]
        + [f"AUROC, {SHORT[s]}" for s in perturbed]
    )
    lines = [
        f"# Learning from the surgeon{' (toy scale)' if toy else ''}",
        "",
        "Gate enforced, scripted surgeon taking over, on the same test seeds for every arm and round "
        f"({rows[0]['test_episodes_per_scenario'] if rows else 0} episodes per scenario). Autonomous: a "
        "success with no handover. Frames: new labelled frames (surgeon effort) this round and so far.",
        "",
        "| " + " | ".join(header) + " |",
        "|" + "---|" * len(header),
    ]
    for row in rows:
        cells = [row["arm"], row["round"], row["new_frames"], row["cumulative_frames"]]
        cells += [_fmt(row["autonomous_success"].get(s)) for s in SCENARIOS]
        cells += [
            _fmt(row["overall_autonomous_success"]),
            _fmt(row["overall_success"]),
            _fmt(row["handovers_per_episode"]),
            _fmt(row["surgeon_steps_per_episode"], 1),
            _fmt(row["nominal_false_alarms_per_episode"]),
        ]
        cells += [_fmt(row["auroc"].get(s)) for s in perturbed]
        lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    if any(row.get("autonomous_change") for row in rows):
        lines += ["", *autonomy_table(rows)]
    lines += ["", "Success (the surgeon's rescues included) per scenario:", ""]
    lines += ["| arm | round | " + " | ".join(SHORT[s] for s in SCENARIOS) + " |"]
    lines += ["|" + "---|" * (2 + len(SCENARIOS))]
    for row in rows:
        cells = [row["arm"], str(row["round"])] + [_fmt(row["success"].get(s)) for s in SCENARIOS]
        lines.append("| " + " | ".join(cells) + " |")
    gated = [r for r in rows if r["arm"] == GATED and r["round"] > 0]
    if any(r.get("collection_handovers", {}).get(TAKEN_OVER) for r in gated):
        lines += [
            "",
            "In the gated arm's collection the surgeon stand-in also took over on its own when the policy's "
            "commands strayed from its own (`--watch.enabled=true`); the evaluations' surgeon takes over only "
            "when the gate hands over. Collection episodes handed over, by who started it:",
            "",
            "| round | the gate | the surgeon |",
            "|---|---|---|",
        ]
        for row in gated:
            counts = row["collection_handovers"]
            lines.append(f"| {row['round']} | {counts.get(GATE_RELEASED, 0)} | {counts.get(TAKEN_OVER, 0)} |")
    lines += ["", "![autonomy and success against surgeon effort](dagger.png)", ""]
    return "\n".join(lines)


def _signed(value: float) -> str:
    return "n/a" if math.isnan(value) else f"{value:+.2f}"


def autonomy_table(rows: list[dict]) -> list[str]:
    """Autonomous success with its Wilson interval, and each round's change from round 0 on the same seeds."""
    lines = [
        "Autonomous success [95% Wilson interval]; from round 1, its change from round 0 on the same test "
        "seeds [95% paired interval, Newcombe], the episodes that became autonomous successes / stopped "
        "being, and McNemar's exact p of no change:",
        "",
        "| arm | round | " + " | ".join(SHORT[s] for s in SCENARIOS) + " |",
        "|" + "---|" * (2 + len(SCENARIOS)),
    ]
    for row in rows:
        intervals, changes = row.get("autonomous_interval", {}), row.get("autonomous_change", {})
        cells = []
        for scenario in SCENARIOS:
            cell = _fmt(row["autonomous_success"].get(scenario))
            if scenario in intervals:
                cell += " [{}, {}]".format(*(_fmt(x) for x in intervals[scenario]))
            change = changes.get(scenario)
            if change:
                lo, hi = change["interval"]
                cell += (
                    f"; {_signed(change['change'])} [{_signed(lo)}, {_signed(hi)}], "
                    f"{change['improved']} / {change['worsened']}, p = {change['p_value']:.2g}"
                )
            cells.append(cell)
        lines.append(f"| {row['arm']} | {row['round']} | " + " | ".join(cells) + " |")
    return lines


def plot(rows: list[dict], out_path: Path) -> Path:
    """Autonomous success (top, with its Wilson interval) and success (bottom) per round against the
    cumulative labelled frames, a column per scenario, each arm its own line, the arms nudged apart along x
    so equal budgets stay visible."""
    fig = Figure(figsize=(4.0 * len(SCENARIOS), 6.4), dpi=100)
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, len(SCENARIOS), sharex=True, sharey=True, squeeze=False)
    span = max([r["cumulative_frames"] for r in rows] + [1])
    arms = [a for a in ARMS if any(r["arm"] == a for r in rows)]
    for column, scenario in enumerate(SCENARIOS):
        for line, key in enumerate(("autonomous_success", "success")):
            ax = axes[line][column]
            for k, arm in enumerate(arms):
                arm_rows = [r for r in rows if r["arm"] == arm]
                nudge = (k - (len(arms) - 1) / 2) * 0.015 * span
                xs = [r["cumulative_frames"] + nudge for r in arm_rows]
                ys = [r[key].get(scenario, math.nan) for r in arm_rows]
                ax.plot(xs, ys, color=COLOURS[arm], marker=MARKERS[arm], lw=1.4, label=arm)
                bounds = [r.get("autonomous_interval", {}).get(scenario) for r in arm_rows]
                if key == "autonomous_success" and all(bounds):
                    below = [max(0.0, y - b[0]) for y, b in zip(ys, bounds, strict=True)]
                    above = [max(0.0, b[1] - y) for y, b in zip(ys, bounds, strict=True)]
                    ax.errorbar(
                        xs, ys, yerr=[below, above], fmt="none", ecolor=COLOURS[arm], alpha=0.5, capsize=2
                    )
                for x, y, r in zip(xs, ys, arm_rows, strict=True):
                    if k == 0 and not math.isnan(y):  # the rounds, once: every arm's lie in the same order
                        ax.annotate(
                            str(r["round"]), (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points"
                        )
            ax.set_ylim(-0.05, 1.05)
            ax.grid(alpha=0.3)
            if line == 0:
                ax.set_title(SHORT[scenario])
            else:
                ax.set_xlabel("cumulative labelled frames")
            if column == 0:
                ax.set_ylabel(
                    "autonomous success" if key == "autonomous_success" else "success (with surgeon)"
                )
    axes[0][0].legend(loc="lower right", fontsize=8)
    fig.suptitle("Autonomy and success per round against surgeon effort (numbers: round)")
    fig.tight_layout()
    out_path = Path(out_path)
    save_figure(fig, out_path)
    return out_path


def write_report(output_dir: Path, arms: list[str], rounds: int, toy: bool = False) -> str:
    """``dagger.md``, ``dagger.json`` and ``dagger.png`` in ``output_dir``; returns the markdown."""
    output_dir = Path(output_dir)
    rows = table_rows(output_dir, arms, rounds)
    text = markdown(rows, toy)
    (output_dir / "dagger.md").write_text(text)
    write_json_atomic(
        output_dir / "dagger.json", {"toy": toy, "scenarios": list(SCENARIOS), "rows": rows}, compact=True
    )
    plot(rows, output_dir / "dagger.png")
    return text
