"""``report.md`` of ``lerobot-suture experiments``: its tables and figures, rendered from ``metrics.json``
alone (a committed ``metrics.json`` renders the same report again)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np


def json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serializable: {type(value).__name__}")


def _fmt(value, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return str(value)


def _interval(bounds) -> str:
    """`` [low, high]`` after a figure; nothing where there is none (one run a side, or older results)."""
    if bounds is None or any(b is None or math.isnan(b) for b in bounds):
        return ""
    return f" [{_fmt(bounds[0])}, {_fmt(bounds[1])}]"


def _settings_note(calibration: dict) -> str:
    settings = calibration.get("score_settings") or {}
    if "uncertainty_samples_per_member" not in settings:
        return ""
    return (
        f", {settings['uncertainty_source']} covariance of {settings['uncertainty_samples_per_member']} "
        "sample(s) per member"
    )


def _by_outcome(by_outcome: dict | None) -> str:
    """Alarmed episodes among the successful and the failed nominal ones (absent from older results)."""
    if not by_outcome:
        return ""
    parts = [
        # Files written before the count was kept hold the rate alone, which is count / episodes.
        f"{rates.get('alarmed_episodes', round(rates['per_episode'] * rates['episodes']))} of "
        f"{rates['episodes']} {outcome}"
        for outcome, rates in by_outcome.items()
        if rates["episodes"]
    ]
    return f" (alarmed episodes: {', '.join(parts)})" if parts else ""


def _end_of_task_lines(end: dict | None) -> list[str]:
    """Where the nominal maxima fall (absent from results written before it was kept)."""
    if not end:
        return []
    if math.isnan(end["share_of_successful_episodes"]):
        return ["", "No nominal episode succeeded, so none says where its largest score falls."]
    return [
        "",
        f"The largest score of {_fmt(end['share_of_successful_episodes'])} of the successful nominal episodes "
        f"falls in their last {end['end_steps']} control steps (the end of the task).",
    ]


def _insertion_lines(insertion: dict | None) -> list[str]:
    """Where the policy's needle crossed the tissue (absent from results written before it was kept)."""
    if not insertion:
        return []
    entry, exit_ = insertion["entry_error_mm"], insertion["exit_error_mm"]
    return [
        f"Where the needle crossed the tissue, over the policy's nominal episodes: entry within "
        f"{_fmt(insertion['entry_tolerance_mm'])} mm of the mark in {_fmt(insertion['entry_within_tolerance'])} "
        f"(median {_fmt(entry['median'])} mm [{_fmt(entry['q25'])}, {_fmt(entry['q75'])}]), exit within "
        f"{_fmt(insertion['exit_tolerance_mm'])} mm in {_fmt(insertion['exit_within_tolerance'])} (median "
        f"{_fmt(exit_['median'])} mm [{_fmt(exit_['q25'])}, {_fmt(exit_['q75'])}]), both in "
        f"{_fmt(insertion['both_within_tolerance'])}; {insertion['never_entered']} never entered, "
        f"{insertion['never_emerged']} never emerged.",
        "",
    ]


def render_report(result: dict) -> str:
    """``report.md``: the results tables and the figures."""
    nominal = result["nominal"]
    low, high = nominal["success_rate_wilson95"]
    e_low, e_high = nominal["expert_success_rate_wilson95"]
    cal = result["calibration"]
    lines = [
        "# Results: safe, uncertainty-aware needle insertion",
        "",
        f"Policy: `{result['policy_path']}`. Gate: {cal['model']} model of the {cal['score_name']} score "
        f"({cal['space']} space{_settings_note(cal)}), {cal['mode']} mode, alpha {cal['alpha']}, "
        f"threshold {_fmt(cal['threshold'], 4)}.",
        "",
        "## In distribution (nominal)",
        "",
        "| | episodes | success | 95% Wilson interval |",
        "|---|---|---|---|",
        f"| policy | {nominal['episodes']} | {_fmt(nominal['success_rate'])} | [{_fmt(low)}, {_fmt(high)}] |",
        f"| scripted expert | {nominal['expert_episodes']} | {_fmt(nominal['expert_success_rate'])} | "
        f"[{_fmt(e_low)}, {_fmt(e_high)}] |",
        "",
        f"False alarms on nominal episodes: {_fmt(nominal['false_alarms']['per_step'])} per step, "
        f"{_fmt(nominal['false_alarms']['per_episode'])} per episode{_by_outcome(nominal.get('false_alarms_by_outcome'))}.",
        *_end_of_task_lines(nominal.get("score_max_in_last_steps")),
        "",
        *_insertion_lines(nominal.get("insertion")),
        "## Out of distribution (gate reporting, as in the paper)",
        "",
        "| experiment | scenario | runs | AUROC vs nominal [95% interval] | AUROC over common steps | TPR at threshold [95% interval] | detection delay (steps), median [IQR] |",
        "|---|---|---|---|---|---|---|",
    ]
    for exp_id, entry in result["experiments"].items():
        d = entry["detection_delay_steps"]
        delay = f"{_fmt(d['median'])} [{_fmt(d['q25'])}, {_fmt(d['q75'])}] (n={d['n']})" if d["n"] else "none"
        lines.append(
            f"| {exp_id} | {entry['scenario']} | {entry['runs']} | "
            f"{_fmt(entry['auroc'])}{_interval(entry.get('auroc_interval95'))} | "
            f"{_fmt(entry.get('auroc_common_steps'))} | "
            f"{_fmt(entry['tpr_at_threshold'])}{_interval(entry.get('tpr_wilson95'))} | {delay} |"
        )
    lines += [
        "",
        "AUROC vs nominal compares each episode's largest score (interval: DeLong's variance); the TPR's "
        "interval is Wilson's. A perturbed run whose throw never "
        "finishes (a dropped needle) goes on to the time limit, past where nominal episodes end. AUROC "
        "over common steps compares each pair of episodes over the control steps both lasted.",
    ]
    lines += ["", "## Control barrier function (experiment 4)", ""]
    replay = result["cbf"]["offline_replay"]
    lines.append(
        f"Offline replay: reference h_min {_fmt(replay.get('h_min_reference'))}, filtered h_min "
        f"{_fmt(replay.get('h_min_safe'))}."
    )
    lines += [
        "",
        "| live arm | runs | violations (h < 0 at a physics step) | min h | intervention rate | tissue strain (m), median |",
        "|---|---|---|---|---|---|",
    ]
    for arm, entry in result["cbf"]["live"].items():
        lines.append(
            f"| {arm} | {entry['runs']} | {entry['violations']} | {_fmt(entry['h_min'])} | "
            f"{_fmt(entry.get('intervention_rate'))} | {_fmt(entry['tissue_strain_m']['median'])} |"
        )
    lines += [
        "",
        "## Gate enforced, scripted surgeon taking over",
        "",
        "| scenario | runs | autonomous success | handover rate | handover step, median | needle in tissue at handover | success after handover | overall success |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for scenario, entry in result["gate_enforced"].items():
        step = (entry.get("handover_step") or {}).get("median")
        lines.append(
            f"| {scenario} | {entry['runs']} | {_fmt(entry['autonomous_success_rate'])} | {_fmt(entry['handover_rate'])} | "
            f"{_fmt(step)} | {_fmt(entry.get('handover_in_tissue_rate'))} | "
            f"{_fmt(entry['success_after_handover_rate'])} | {_fmt(entry['success_rate'])} |"
        )
    lines += ["", "## Figures", ""]
    for exp_id, name in result["figures"].items():
        lines.append(f"![experiment {exp_id}]({name})")
    lines.append("")
    return "\n".join(lines)
