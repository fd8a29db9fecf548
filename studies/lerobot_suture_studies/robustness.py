"""``lerobot-suture robustness-report``: policies side by side under the shifts, inside and beyond what
their training data varied, with the gate's flags and the paper's bars.

Reads, for each policy, the ``detectors.json`` that ``lerobot-suture benchmark-ood`` wrote (and, optionally,
the ``metrics.json`` of ``lerobot-suture experiments``) or its row of a ``lerobot-suture leaderboard`` board
(fifty episodes a shift cell, with Wilson intervals), and writes ``robustness.md``, ``robustness.json`` and
``robustness.png`` into ``output_dir``:

- per shift x magnitude and policy: success, flagged of the failed runs, flagged of the successful runs,
  and whether the magnitude lies inside the policy's training range (its dataset's appearance
  randomization), beyond it, or varies something no recipe randomizes (``untrained``);
- per policy, the bars: the smallest success inside the training ranges; beyond them, the share of failed
  runs the gate flags and of successful runs it flags (pooled over shifts), and what any threshold on the
  gate's score could do there (how well it ranks failed runs above successful ones, and the most failed
  runs it flags at the bar's share of successful ones: a hindsight bound on calibration); and, from the
  experiments, the paper-scenario figures (nominal success, AUROC of the drop and of the phantom moved
  after insertion, servo runs flagged, drop delay, false alarms).

From a benchmark the gate is its ``detector`` row (the ensemble's covariance by default), calibrated as the
benchmark calibrates it: per-episode threshold at alpha on nominal validation runs of the training
distribution. From a leaderboard it is the policy's own calibrated gate, as the board ran it (no per-run
scores: the any-threshold figures are n/a).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from lerobot_suture.experiments.metrics import auroc, most_failures_flagged
from lerobot_suture.leaderboard.cells import condition_shift
from lerobot_suture.plotting import save_figure
from lerobot_suture.runtime.calibration import dataset_appearance
from lerobot_suture.sim.shifts import Shift, within_training_range
from lerobot_suture_studies.benchmark_ood_report import fmt

RANGE_LABELS = {True: "inside", False: "beyond", None: "untrained"}
BEYOND_SUCCESSES_FLAGGED_BAR = 0.15
"""Beyond the ranges, the most successful runs the gate may flag (the bar)."""


def _named_dirs(values: list[str], what: str) -> dict[str, Path]:
    out = {}
    for value in values:
        name, sep, path = value.partition("=")
        if not sep or not name or not path:
            raise ValueError(
                f"`{what}` entries are NAME=DIR (e.g. robust=outputs/bench_robust). Got {value!r}."
            )
        out[name] = Path(path)
    return out


@dataclass
class RobustnessReportConfig:
    """Args:
    runs: ``NAME=DIR`` of each policy's benchmark-ood output (holding ``detectors.json``), baseline first.
    experiments: ``NAME=DIR`` of the same policies' experiments outputs (holding ``metrics.json``); optional.
    detector: the benchmark row that plays the gate.
    leaderboard: a ``leaderboard.json`` of ``lerobot-suture leaderboard`` to read ``rows`` from.
    rows: ``NAME=ROW`` of each policy's row on the leaderboard's ``task`` (after the ``runs``).
    task: the leaderboard task whose shift cells are read.
    training_data: ``NAME=DATASET_ROOT`` of each leaderboard row whose training data was recorded with
        appearance randomization (its ranges decide inside / beyond; a row not named is untrained).
    output_dir: where ``robustness.md``, ``robustness.json`` and ``robustness.png`` go.
    """

    runs: list[str] = field(default_factory=list)
    experiments: list[str] = field(default_factory=list)
    detector: str = "ensemble_covariance"
    leaderboard: Path | None = None
    rows: list[str] = field(default_factory=list)
    task: str = "insertion"
    training_data: list[str] = field(default_factory=list)
    output_dir: Path = Path("outputs/robustness")

    def __post_init__(self):
        if not self.runs and not self.rows:
            raise ValueError(
                "Name at least one policy: --runs='[reference=DIR]' (benchmark-ood outputs) or "
                "--leaderboard=docs/results/leaderboard/leaderboard.json --rows='[reference=ensemble_diffusion]'."
            )
        # Parsed once here; build_report reads these.
        self.named_runs = _named_dirs(self.runs, "runs")
        self.named_experiments = _named_dirs(self.experiments, "experiments")
        self.named_rows = _named_dirs(self.rows, "rows")
        self.named_training_data = _named_dirs(self.training_data, "training_data")
        for name, path in self.named_runs.items():
            if not (path / "detectors.json").is_file():
                raise ValueError(
                    f"{path} (run {name}) holds no detectors.json: run `lerobot-suture benchmark-ood "
                    f"--output_dir={path}` first."
                )
        for name, path in self.named_experiments.items():
            if not (path / "metrics.json").is_file():
                raise ValueError(f"{path} (experiments {name}) holds no metrics.json.")
        rows = {name: str(row) for name, row in self.named_rows.items()}
        if rows:
            if self.leaderboard is None or not Path(self.leaderboard).is_file():
                raise ValueError(
                    f"`rows` are read from a leaderboard: pass --leaderboard=PATH/leaderboard.json (got "
                    f"{self.leaderboard})."
                )
            board = json.loads(Path(self.leaderboard).read_text()).get("tasks", {}).get(self.task, {})
            missing = sorted(set(rows.values()) - set(board))
            if missing:
                raise ValueError(
                    f"The leaderboard {self.leaderboard} has no row {missing} on task {self.task!r}; its rows: "
                    f"{sorted(board)}."
                )
        clash = sorted(set(rows) & set(self.named_runs))
        if clash:
            raise ValueError(f"{clash} name both a run and a leaderboard row: give each policy one name.")
        for name, root in self.named_training_data.items():
            if not (root / "meta" / "info.json").is_file():
                raise ValueError(
                    f"`training_data` {name}={root} holds no LeRobotDataset (no meta/info.json)."
                )
        stray = sorted(set(self.named_training_data) - set(rows))
        if stray:
            raise ValueError(
                f"`training_data` names {stray}, which are not leaderboard rows (a benchmark run keeps its own)."
            )


def shift_rows(benchmark: dict, detector: str) -> list[dict]:
    """One row per shift of a benchmark: success, the gate's flags, the range status."""
    if detector not in benchmark["detectors"] or "error" in benchmark["detectors"][detector]:
        raise ValueError(f"The benchmark has no result for detector {detector!r}.")
    gate = benchmark["detectors"][detector]["shifts"]
    rows = []
    for label in benchmark.get("shifts", []):
        m = gate[label]
        shift = Shift.parse(label)
        rows.append(
            {
                "shift": label,
                "family": shift.family,
                "range": RANGE_LABELS[within_training_range(shift, benchmark.get("training_appearance"))],
                "runs": m["runs"],
                "failures": m["failures"],
                "success_rate": m["success_rate"],
                "flagged_of_failures": m["flagged_of_failures"],
                "flagged_of_successes": m["flagged_of_successes"],
                # Per run (benchmarks from before these were kept have none): any threshold's flags.
                "run_max_scores": m.get("run_max_scores"),
                "run_successes": m.get("run_successes"),
            }
        )
    return rows


def cell_shift_rows(row: dict, training_appearance: dict | None) -> list[dict]:
    """One row per shift cell of a leaderboard row, with :func:`shift_rows`' fields and the success's Wilson
    interval; the gate is the policy's own (a row without one has nothing to report here)."""
    rows = []
    for condition, cell in row.items():
        shift = condition_shift(condition)
        if shift is None:
            continue
        if cell["gate"] is None:
            raise ValueError(f"The row's cell {condition} has no gate (the policy has no O.O.D. gate).")
        runs, successes, gate = cell["episodes"], cell["successes"], cell["gate"]
        failures = runs - successes
        rows.append(
            {
                "shift": shift.label,
                "family": shift.family,
                "range": RANGE_LABELS[within_training_range(shift, training_appearance)],
                "runs": runs,
                "failures": failures,
                "success_rate": cell["success_rate"],
                "success_interval": cell["success_interval"],
                "flagged_of_failures": gate["flagged_failures"] / failures if failures else math.nan,
                "flagged_of_successes": (gate["flagged"] - gate["flagged_failures"]) / successes
                if successes
                else math.nan,
                "run_max_scores": None,
                "run_successes": None,
            }
        )
    return rows


def _pooled(rows: list[dict], key: str, count) -> float:
    n = sum(count(r) for r in rows)
    flagged = sum(r[key] * count(r) for r in rows if count(r))
    return flagged / n if n else math.nan


def _any_threshold(beyond: list[dict]) -> dict:
    """Beyond the ranges, what the gate's score could do with any threshold: how well its per-run maxima
    rank the failed runs above the successful ones (AUROC), and the most failed runs a threshold flags
    while flagging at most the bar's share of successful ones. nan without per-run scores."""
    if not beyond or any(r.get("run_max_scores") is None for r in beyond):
        return {"beyond_failure_auroc": math.nan, "beyond_most_failures_flagged_at_bar": math.nan}
    pairs = [p for r in beyond for p in zip(r["run_max_scores"], r["run_successes"], strict=True)]
    failed = [x for x, ok in pairs if not ok]
    succeeded = [x for x, ok in pairs if ok]
    return {
        "beyond_failure_auroc": auroc(succeeded, failed),
        "beyond_most_failures_flagged_at_bar": most_failures_flagged(
            failed, succeeded, BEYOND_SUCCESSES_FLAGGED_BAR
        ),
    }


def bars(rows: list[dict], metrics: dict | None) -> dict:
    """The issue's bars for one policy: inside the ranges, beyond them (pooled), and the paper's."""
    inside = [r for r in rows if r["range"] == "inside"]
    beyond = [r for r in rows if r["range"] != "inside"]
    out = {
        "min_success_inside_range": min((r["success_rate"] for r in inside), default=math.nan),
        "beyond_failed_runs": sum(r["failures"] for r in beyond),
        "beyond_flagged_of_failures": _pooled(beyond, "flagged_of_failures", lambda r: r["failures"]),
        "beyond_flagged_of_successes": _pooled(
            beyond, "flagged_of_successes", lambda r: r["runs"] - r["failures"]
        ),
        **_any_threshold(beyond),
    }
    if metrics:
        e = metrics["experiments"]
        out.update(
            {
                "nominal_success": metrics["nominal"]["success_rate"],
                "nominal_false_alarms_per_episode": metrics["nominal"]["false_alarms"]["per_episode"],
                "needle_drop_auroc": e["1"]["auroc"],
                "after_insertion_auroc": e["3.2"]["auroc"],
                "servo_flagged": e["3.1"]["tpr_at_threshold"],
                "needle_drop_delay_steps": e["1"]["detection_delay_steps"]["median"],
                "camera_moved_success": e["2"]["policy_success_rate"],
                "camera_moved_flagged": e["2"]["tpr_at_threshold"],
            }
        )
    return out


def render(result: dict) -> str:
    names = list(result["policies"])
    lines = [
        "# Robustness under shifts",
        "",
        "Each cell: success (with its 95% Wilson interval where the source keeps it); flagged of the failed "
        "runs / flagged of the successful runs. Range: inside or beyond the appearance range the policy's "
        "data was randomized over, or untrained (no recipe varies it). The gate of each policy:",
        "",
        *[f"- {n}: {result['policies'][n]['gate']}" for n in names],
        "",
        "| shift | family | "
        + " | ".join(f"{n}: range | {n}: success | {n}: flagged F / S" for n in names)
        + " |",
        "|---|---|" + "---|---|---|" * len(names),
    ]
    by_policy = {n: {r["shift"]: r for r in result["policies"][n]["shifts"]} for n in names}
    for label in result["shifts"]:
        cells = []
        for n in names:
            r = by_policy[n].get(label)
            if r is None:
                cells += ["", "", ""]
                continue
            success = fmt(r["success_rate"], 2)
            if r.get("success_interval"):
                success += " [{:.2f}, {:.2f}]".format(*r["success_interval"])
            cells += [
                r["range"],
                success,
                f"{fmt(r['flagged_of_failures'], 2)} / {fmt(r['flagged_of_successes'], 2)}",
            ]
        lines.append(f"| {label} | {Shift.parse(label).family} | " + " | ".join(cells) + " |")
    keys = [
        ("min_success_inside_range", "smallest success inside the training ranges (bar >= 0.80)"),
        ("beyond_flagged_of_failures", "beyond: failed runs flagged (bar >= 0.90)"),
        (
            "beyond_flagged_of_successes",
            f"beyond: successful runs flagged (bar <= {BEYOND_SUCCESSES_FLAGGED_BAR})",
        ),
        ("beyond_failed_runs", "beyond: failed runs"),
        ("beyond_failure_auroc", "beyond, any threshold: failed runs scored above successful ones (AUROC)"),
        (
            "beyond_most_failures_flagged_at_bar",
            "beyond, any threshold: most failed runs flagged with <= "
            f"{BEYOND_SUCCESSES_FLAGGED_BAR} of successful runs flagged",
        ),
        ("nominal_success", "nominal success (bar >= 0.90)"),
        ("needle_drop_auroc", "needle drop AUROC (bar >= 0.95)"),
        ("after_insertion_auroc", "phantom moved after insertion AUROC (bar >= 0.95)"),
        ("servo_flagged", "phantom servo flagged (bar <= 0.20)"),
        ("needle_drop_delay_steps", "needle drop median delay, steps (bar <= 10)"),
        ("nominal_false_alarms_per_episode", "nominal false alarms per episode (bar <= 0.05)"),
        ("camera_moved_success", "camera moved: success"),
        ("camera_moved_flagged", "camera moved: flagged"),
    ]
    lines += ["", "| figure | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for key, what in keys:
        values = [result["policies"][n]["bars"].get(key) for n in names]
        if all(v is None for v in values):
            continue
        digits = 0 if key in ("beyond_failed_runs", "needle_drop_delay_steps") else 2
        lines.append(f"| {what} | " + " | ".join(fmt(v, digits) for v in values) + " |")
    return "\n".join(lines) + "\n"


def plot(result: dict, path: Path) -> Path:
    """Success per shift, a bar per policy; the gate's flags of failed (filled) and successful (open) runs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    names, shifts = list(result["policies"]), result["shifts"]
    x = np.arange(len(shifts))
    width = 0.8 / len(names)
    fig, ax = plt.subplots(figsize=(max(9.0, 0.6 * len(shifts) + 6), 5.0))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for k, name in enumerate(names):
        rows = {r["shift"]: r for r in result["policies"][name]["shifts"]}
        xs = x - 0.4 + width * (k + 0.5)
        colour = colours[k % len(colours)]

        def get(key, rows=rows):
            return [rows[s][key] if s in rows else math.nan for s in shifts]

        ax.bar(xs, get("success_rate"), width * 0.9, color=colour, alpha=0.35, label=f"{name}: success")
        ax.plot(xs, get("flagged_of_failures"), "v", color=colour, ms=6, label=f"{name}: failed runs flagged")
        ax.plot(xs, get("flagged_of_successes"), "o", mfc="none", color=colour, ms=6,
                label=f"{name}: successful runs flagged")  # fmt: skip
        for xi, s in zip(xs, shifts, strict=True):
            if s in rows and rows[s]["range"] == "inside":
                ax.text(xi, 1.04, "in", ha="center", fontsize=6, color=colour)
    ax.set_xticks(x, shifts, rotation=60, ha="right", fontsize=8)
    ax.set_ylim(0, 1.1)
    ax.set_ylabel("share of runs")
    ax.set_title(
        "Success under each shift (bars) and the gate's flags; 'in': inside the training range", fontsize=9
    )
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)
    return path


def build_report(cfg: RobustnessReportConfig) -> dict:
    runs, experiments = cfg.named_runs, cfg.named_experiments
    policies, shifts = {}, []
    for name, path in runs.items():
        benchmark = json.loads((path / "detectors.json").read_text())
        try:
            rows = shift_rows(benchmark, cfg.detector)
        except ValueError as exc:
            raise ValueError(
                f"Run {name!r} ({path}): {exc} Run `lerobot-suture benchmark-ood` on that policy again with "
                "the same arguments (it rescores the saved rollouts), or choose another `--detector`."
            ) from exc
        metrics = None
        if name in experiments:
            metrics = json.loads((experiments[name] / "metrics.json").read_text())
        policies[name] = {
            "benchmark": str(path),
            "gate": f"the `{cfg.detector}` detector of `lerobot-suture benchmark-ood` ({path}), thresholded "
            "per episode on nominal validation runs of its training distribution",
            "policy_success_rate": benchmark["policy_success_rate"],
            "training_appearance": benchmark.get("training_appearance"),
            "shifts": rows,
            "bars": bars(rows, metrics),
        }
        shifts += [r["shift"] for r in rows if r["shift"] not in shifts]
    if cfg.rows:
        board = json.loads(Path(cfg.leaderboard).read_text())
        data = cfg.named_training_data
        for name, row_name in cfg.named_rows.items():
            row = board["tasks"][cfg.task][str(row_name)]
            appearance = dataset_appearance(data.get(name)).get("appearance")
            try:
                rows = cell_shift_rows(row, appearance)
            except ValueError as exc:
                raise ValueError(f"Leaderboard row {row_name!r}: {exc}") from exc
            policies[name] = {
                "leaderboard": f"{cfg.leaderboard}: {cfg.task} / {row_name}",
                "gate": f"its own calibrated gate, row `{row_name}` of {cfg.leaderboard} "
                f"({board['episodes']} episodes a cell, seeds from {board['seed']})",
                "policy_success_rate": {c: cell["success_rate"] for c, cell in row.items()},
                "training_appearance": appearance,
                "shifts": rows,
                "bars": bars(rows, None),
            }
            shifts += [r["shift"] for r in rows if r["shift"] not in shifts]
    result = {"detector": cfg.detector, "shifts": shifts, "policies": policies}
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    (cfg.output_dir / "robustness.json").write_text(json.dumps(result, separators=(",", ":")))
    (cfg.output_dir / "robustness.md").write_text(render(result))
    plot(result, cfg.output_dir / "robustness.png")
    return result
