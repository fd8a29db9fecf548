"""What ``lerobot-suture benchmark-ood`` writes for people: ``detectors.md`` and the figures."""

from __future__ import annotations

import math
from pathlib import Path

from lerobot_suture.experiments.paper import EXPERIMENTS
from lerobot_suture.plotting import save_figure

SCENARIOS = tuple(scenario for _, scenario, _ in EXPERIMENTS)


def fmt(x, digits: int = 3) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def _delay(summary: dict) -> str:
    return "none" if not summary["n"] else f"{summary['median']:.0f} ({summary['n']})"


def _ok(r: dict) -> bool:
    return "error" not in r


def render_tables(result: dict) -> str:
    """``detectors.md``: a summary row per detector, one detectors x metrics table per scenario, the
    shifts table, and where each detector's nominal alarms fall."""
    episodes = result["episodes"]
    shifts = result.get("shifts", [])
    lines = [
        f"# Failure detectors: {result['policy_path']}",
        "",
        f"Fitted on {episodes['fit']} nominal episodes and thresholded on {episodes['calibration']} more "
        f"(validation seeds from {result['validation_seed']}; per-episode conformal threshold at alpha = "
        f"{result['alpha']}"
        + ("; under the training dataset's appearance ranges" if result.get("training_appearance") else "")
        + f"); measured on {episodes['nominal']} nominal episodes, the paper's four scenarios"
        + (f" and {len(shifts)} shifts" if shifts else "")
        + f" (test seeds from {result['test_seed']}). Cost: the detector's own scoring time, on top of "
        "the policy's inference (the score is computed at each new prediction and held in between).",
        "",
        "| detector | false alarms / nominal episode | mean AUROC | mean AUROC (common steps) "
        "| ms / prediction | ms / control step | fit (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    detectors = result["detectors"]
    for name, r in detectors.items():
        if not _ok(r):
            lines.append(f"| {name} | failed: {r['error']} | | | | | |")
            continue
        c = r["cost"]
        lines.append(
            f"| {name} | {fmt(r['false_alarms']['per_episode'], 2)} | {fmt(r['mean_auroc'])} | "
            f"{fmt(r['mean_auroc_common_steps'])} | {fmt(c['ms_per_prediction'], 2)} | "
            f"{fmt(c['ms_per_control_step'], 3)} | {fmt(c['fit_s'], 2)} |"
        )
    for scenario in SCENARIOS:
        lines += [
            "",
            f"## {scenario} ({episodes[scenario]} runs, policy success "
            f"{fmt(result['policy_success_rate'][scenario], 2)})",
            "",
            "| detector | AUROC | AUROC (common steps) | TPR at threshold | false alarms before onset / episode "
            "| median delay, steps (detected) | failure-prediction balanced accuracy |",
            "|---|---|---|---|---|---|---|",
        ]
        for name, r in detectors.items():
            if not _ok(r):
                continue
            m = r["scenarios"][scenario]
            lines.append(
                f"| {name} | {fmt(m['auroc'])} | {fmt(m['auroc_common_steps'])} | "
                f"{fmt(m['tpr_at_threshold'], 2)} | {fmt(m['false_alarm_before_onset_per_episode'], 2)} | "
                f"{_delay(m['detection_delay_steps'])} | {fmt(m['failure_prediction_balanced_accuracy'])} |"
            )
    names = [n for n, r in detectors.items() if _ok(r)]
    if shifts and names:
        lines += [
            "",
            "## Shifts",
            "",
            "Each shift at each magnitude, in the nominal scenario. Per detector: flagged of the failed runs / "
            "flagged of the successful runs (an alarm anywhere in the run). A good gate flags what fails "
            "and spares what succeeds.",
            "",
            "| shift | runs | policy success | " + " | ".join(names) + " |",
            "|---|---|---|" + "---|" * len(names),
        ]
        for label in shifts:
            cells = []
            for name in names:
                m = detectors[name]["shifts"][label]
                cells.append(f"{fmt(m['flagged_of_failures'], 2)} / {fmt(m['flagged_of_successes'], 2)}")
            lines.append(
                f"| {label} | {episodes[label]} | {fmt(result['policy_success_rate'][label], 2)} | "
                + " | ".join(cells)
                + " |"
            )
        lines += [
            "",
            "Failure-prediction balanced accuracy over all shifted and nominal runs (mean over shifts):",
            "",
            "| detector | mean balanced accuracy | mean AUROC vs nominal |",
            "|---|---|---|",
        ]
        for name in names:
            ms = detectors[name]["shifts"].values()
            ba = [m["failure_prediction_balanced_accuracy"] for m in ms]
            au = [m["auroc"] for m in ms]
            lines.append(f"| {name} | {fmt(_mean(ba))} | {fmt(_mean(au))} |")
    if names:
        steps = result.get("approach_steps")
        lines += [
            "",
            f"## Where nominal alarms fall (approach: the first {steps} control steps)",
            "",
            "| detector | nominal alarms | raised in the approach | median max-score ratio, approach / rest |",
            "|---|---|---|---|",
        ]
        for name in names:
            a = detectors[name]["approach"]
            lines.append(
                f"| {name} | {a['alarms']} | {a['in_approach']} | {fmt(a['approach_to_rest_max_ratio'], 2)} |"
            )
    return "\n".join(lines) + "\n"


def _mean(values) -> float:
    finite = [v for v in values if v is not None and not math.isnan(v)]
    return sum(finite) / len(finite) if finite else math.nan


def plot_detector(name: str, result: dict, path: Path) -> Path:
    """One panel per scenario: the detector's held scores over control steps, nominal test episodes in
    grey, scenario runs in colour (red: failed, blue: succeeded), onsets as dots, the threshold dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    traces = result["traces"]
    fig, axes = plt.subplots(2, 2, figsize=(10, 6.5), sharey=True)
    for ax, scenario in zip(axes.flat, SCENARIOS, strict=True):
        for run in traces["nominal"]:
            ax.plot(run["scores"], color="0.6", lw=0.8, alpha=0.6)
        for run in traces[scenario]:
            colour = "tab:blue" if run["success"] else "tab:red"
            ax.plot(run["scores"], color=colour, lw=1.0)
            if run["onset"] is not None:
                ax.plot(run["onset"], run["scores"][run["onset"]], "o", color=colour, ms=4)
        ax.axhline(result["threshold"], color="k", ls="--", lw=1.0, label="threshold")
        m = result["scenarios"][scenario]
        ax.set_title(
            f"{scenario}: AUROC {fmt(m['auroc'], 2)}, TPR {fmt(m['tpr_at_threshold'], 2)}", fontsize=9
        )
        ax.set_xlabel("control step", fontsize=8)
    axes[0, 0].set_ylabel(f"{name} score")
    axes[1, 0].set_ylabel(f"{name} score")
    axes[0, 0].legend(fontsize=7, loc="upper left")
    fig.suptitle(
        f"{name}: grey nominal (test seeds), red failed and blue successful runs, dots at the onset",
        fontsize=10,
    )
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)
    return path


def plot_shifts(per_detector: dict, shifts: list[str], path: Path) -> Path:
    """Per shift: the policy's success (bars) and, per detector, the share of failed runs flagged (filled
    markers) and of successful runs flagged (open markers)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    names = [n for n, r in per_detector.items() if _ok(r)]
    first = per_detector[names[0]]["shifts"]
    x = np.arange(len(shifts))
    fig, ax = plt.subplots(figsize=(max(8.0, 0.55 * len(shifts) + 5), 4.8))
    ax.bar(x, [first[s]["success_rate"] for s in shifts], color="0.85", label="policy success")
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    width = 0.7 / max(len(names), 1)
    for k, name in enumerate(names):
        m = per_detector[name]["shifts"]
        dx = -0.35 + width * (k + 0.5)
        colour = colours[k % len(colours)]
        ax.plot(x + dx, [m[s]["flagged_of_failures"] for s in shifts], "o", color=colour, ms=5, label=name)
        ax.plot(x + dx, [m[s]["flagged_of_successes"] for s in shifts], "o", mfc="none", color=colour, ms=5)
    ax.set_xticks(x, shifts, rotation=60, ha="right", fontsize=8)
    ax.set_ylim(-0.03, 1.03)
    ax.set_ylabel("share of runs")
    ax.set_title(
        "Grey: policy success. Filled: failed runs flagged. Open: successful runs flagged.", fontsize=9
    )
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)
    return path
