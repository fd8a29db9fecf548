"""A new run's ``metrics.json`` beside a committed one, each row marked within or outside its tolerance.

Tolerances (stated once, here):

- a **rate** (a success rate, a false-alarm rate, a true-positive rate over ``n`` runs) is within when the
  new rate lies in the committed run's 95% Wilson interval for its own ``n``;
- an **AUROC** is within ``AUROC_BAND`` of the committed one;
- a **median detection delay** is within ``DELAY_BAND_STEPS`` control steps (both undefined also agrees:
  no run was flagged in either);
- a **count of CBF violations** must be equal: the filter's guarantee is not statistical.

Pure functions of two ``metrics.json`` dicts as ``lerobot-suture experiments`` writes them.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from lerobot_suture.experiments.metrics import wilson_interval

AUROC_BAND = 0.05
DELAY_BAND_STEPS = 2.0

_EXPERIMENTS = {
    "1": "needle drop",
    "2": "camera moved",
    "3.1": "phantom servo",
    "3.2": "phantom moved after insertion",
}


@dataclass(frozen=True)
class Row:
    """One compared figure: its name, both values, the tolerance in words and the verdict."""

    name: str
    committed: float | None
    new: float | None
    tolerance: str
    within: bool


def _rate_row(name: str, committed_rate: float, committed_n: int, new_rate: float | None) -> Row:
    low, high = wilson_interval(round(committed_rate * committed_n), committed_n)
    within = new_rate is not None and low - 1e-12 <= new_rate <= high + 1e-12
    return Row(
        name, committed_rate, new_rate, f"95% interval [{low:.3f}, {high:.3f}] (n={committed_n})", within
    )


def _band_row(name: str, committed: float | None, new: float | None, band: float, unit: str) -> Row:
    tolerance = f"+-{band:g} {unit}".rstrip() + "; undefined only beside undefined"
    if committed is None or new is None:
        return Row(name, committed, new, tolerance, committed is None and new is None)
    return Row(name, committed, new, tolerance, abs(new - committed) <= band + 1e-12)


def _get(metrics: dict, *keys: str):
    value = metrics
    for key in keys:
        if not isinstance(value, dict) or key not in value:
            return None
        value = value[key]
    return value


def compare_metrics(committed: dict, new: dict) -> list[Row]:
    """Rows for the headline figures of two experiment runs (committed first, then the new one)."""
    nominal = committed["nominal"]
    rows = [
        _rate_row(
            "nominal success, policy",
            nominal["success_rate"],
            nominal["episodes"],
            _get(new, "nominal", "success_rate"),
        ),
        _rate_row(
            "nominal success, scripted expert",
            nominal["expert_success_rate"],
            nominal["expert_episodes"],
            _get(new, "nominal", "expert_success_rate"),
        ),
        _rate_row(
            "nominal false alarms per episode",
            nominal["false_alarms"]["per_episode"],
            nominal["false_alarms"]["episodes"],
            _get(new, "nominal", "false_alarms", "per_episode"),
        ),
    ]
    for key, label in _EXPERIMENTS.items():
        old = committed["experiments"].get(key)
        if old is None:
            continue
        rows.append(
            _band_row(
                f"{key} {label}: AUROC", old["auroc"], _get(new, "experiments", key, "auroc"), AUROC_BAND, ""
            )
        )
        rows.append(
            _rate_row(
                f"{key} {label}: flagged (TPR at threshold)",
                old["tpr_at_threshold"],
                old["runs"],
                _get(new, "experiments", key, "tpr_at_threshold"),
            )
        )
        rows.append(
            _band_row(
                f"{key} {label}: detection delay, median",
                old["detection_delay_steps"]["median"],
                _get(new, "experiments", key, "detection_delay_steps", "median"),
                DELAY_BAND_STEPS,
                "steps",
            )
        )
    for arm in ("policy_filter_on", "adversary_filter_on"):
        old = _get(committed, "cbf", "live", arm, "violations")
        if old is not None:
            value = _get(new, "cbf", "live", arm, "violations")
            rows.append(Row(f"CBF {arm.replace('_', ' ')}: violations", old, value, "equal", value == old))
    for scenario, old in (committed.get("gate_enforced") or {}).items():
        rows.append(
            _rate_row(
                f"gate enforced, {scenario.replace('_', ' ')}: overall success",
                old["success_rate"],
                old["runs"],
                _get(new, "gate_enforced", scenario, "success_rate"),
            )
        )
    return rows


def _fmt(value: float | None) -> str:
    if value is None:
        return "n/a"
    return f"{value:.3g}" if isinstance(value, float) else str(value)


def comparison_markdown(rows: list[Row], committed_label: str, new_label: str) -> str:
    within = sum(r.within for r in rows)
    lines = [
        f"| figure | {committed_label} | {new_label} | tolerance | within |",
        "|---|---|---|---|---|",
        *(
            f"| {r.name} | {_fmt(r.committed)} | {_fmt(r.new)} | {r.tolerance} | {'yes' if r.within else '**no**'} |"
            for r in rows
        ),
        "",
        f"{within} of {len(rows)} rows within tolerance.",
    ]
    return "\n".join(lines)


def comparison_json(rows: list[Row]) -> list[dict]:
    return [asdict(r) for r in rows]
