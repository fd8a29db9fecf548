"""A gate per stage on the chained running suture: calibrated on successful sutures, tested on the board's seeds.

The chain (``lerobot-suture chain``; its subtask policies ensembles or members) runs with the high level's
subtask and every prediction's score logged (``runtime.gates.StageGates``, recording only), the CBF on:

1. on ``--calibration-episodes`` fresh nominal seeds (the gate calibration's own, disjoint from every test seed).
   Of the sutures that closed (FAIL-Detect's convention), each scored subtask's segments give its threshold, the
   split-conformal quantile at ``--alpha`` of their largest scores (``runtime.calibration.stage_thresholds``), and
   every subtask's segment lengths give its time budget at the same ``alpha`` (``fit_stage_budgets``). Both are
   written to ``--work-dir`` (``stage_calibration.json``, ``stage_budgets.json``), where
   ``benchmarks/chain_interventions.py --stage-dir`` reads them to enforce the gate.
2. on the leaderboard's test seeds of the running suture: ``--episodes`` nominal (the policy's own failures) and
   ``--scenario-episodes`` in each perturbation scenario. Each suture is replayed through the gate
   (``experiments.stage_alarms``): a failing suture is caught when a flag falls before its failing throw ends, and a
   successful one flagged is a false alarm. The bar: >= 80% of failing sutures caught, <= 10% of successful ones
   flagged.

Each run's episodes are kept in ``--work-dir`` (a rerun reads them back). Prints one JSON object; ``--plot``
draws the caught and flagged shares per condition::

    .venv/bin/python benchmarks/stage_gate.py --chain CHAIN_DIR --work-dir outputs/stage_gate \\
        --regrasp-from release --arc-guard
"""

from __future__ import annotations

import argparse
import pickle
import time
from pathlib import Path

from _report import emit, machine

NEEDS = "a chain written by `lerobot-suture chain` (--chain) whose chained sutures close"
TASK = "running_suture"
CATCH_BAR, FALSE_ALARM_BAR = 0.8, 0.1


def rollouts(runner, env_kwargs, chain_config, condition, seeds, batch_envs, path: Path, desc: str):
    """The episodes of ``seeds`` under ``condition``, scores and subtasks logged; read back from ``path`` when a
    run before this one finished them."""
    from lerobot_suture.leaderboard import cells
    from lerobot_suture.runtime.gates import ReportingGates, StageGates

    if path.is_file():
        return pickle.loads(path.read_bytes())
    print(f"{desc}: {len(seeds)} sutures, {condition} ...", flush=True)
    gates = StageGates(ReportingGates(runner.policy), None, rules=chain_config.rules)
    start = time.perf_counter()
    logs, _ = cells.cell_episodes(runner, env_kwargs, TASK, condition, seeds, batch_envs, gates=gates)
    seconds = time.perf_counter() - start
    path.write_bytes(pickle.dumps((logs, seconds)))
    return logs, seconds


def figure(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from lerobot_suture.plotting import save_figure

    names = list(report["conditions"])
    fig, ax = plt.subplots(figsize=(8, 4))
    x = np.arange(len(names))
    for offset, key, label in (
        (-0.2, "failing_caught", "failing sutures caught before the failing throw ends"),
        (0.2, "successful_flagged", "successful sutures flagged"),
    ):
        rates = [report["conditions"][n][key] for n in names]
        values = [r["rate"] if r["rate"] is not None else np.nan for r in rates]
        low = [max(v - r["wilson_95"][0], 0) if r["of"] else 0 for v, r in zip(values, rates, strict=True)]
        high = [max(r["wilson_95"][1] - v, 0) if r["of"] else 0 for v, r in zip(values, rates, strict=True)]
        ax.bar(x + offset, values, 0.4, yerr=[low, high], capsize=3, label=label)
    ax.axhline(CATCH_BAR, color="C0", linestyle=":")
    ax.axhline(FALSE_ALARM_BAR, color="C1", linestyle=":")
    labels = [n.replace("_after_insertion", " after\ninsertion").replace("_", " ") for n in names]
    ax.set_xticks(
        x,
        [f"{label}\n({report['conditions'][n]['episodes']})" for label, n in zip(labels, names, strict=True)],
    )
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("share of sutures")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title("A gate per stage on the chained running suture (95% Wilson; bars dotted)")
    save_figure(fig, path)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--chain", type=Path, required=True, help="a directory `lerobot-suture chain` wrote")
    parser.add_argument("--work-dir", type=Path, required=True, help="the runs and the fit (rerun: resume)")
    parser.add_argument("--calibration-episodes", type=int, default=88)
    parser.add_argument("--episodes", type=int, default=50, help="nominal test sutures")
    parser.add_argument(
        "--scenario-episodes", type=int, default=10, help="test sutures per scenario (0: none)"
    )
    parser.add_argument("--seed", type=int, default=7_000_000, help="the leaderboard's base of test seeds")
    parser.add_argument("--alpha", type=float, default=0.01, help="the per-segment false-alarm rate")
    parser.add_argument(
        "--scored", nargs="+", default=["insert", "lay_down"], help="the subtasks a learned policy serves"
    )
    parser.add_argument("--batch-envs", type=int, default=8)
    parser.add_argument("--regrasp-from", choices=("marks", "release"), default="marks")
    parser.add_argument("--arc-guard", action="store_true", help="hold the needle in tissue to its arc")
    parser.add_argument("--output", type=Path)
    parser.add_argument("--plot", type=Path)
    args = parser.parse_args()

    from lerobot_suture.experiments.stage_alarms import stage_alarm_table, stage_durations
    from lerobot_suture.leaderboard import cells
    from lerobot_suture.runtime.calibration import stage_thresholds
    from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy
    from lerobot_suture.runtime.seeds import fresh_seeds
    from lerobot_suture.safety.ood.stage_gate import fit_stage_budgets
    from lerobot_suture.sim.tasks import task_spec

    args.work_dir.mkdir(parents=True, exist_ok=True)
    runner = PolicyRunner.from_pretrained(args.chain, GateMode.REPORT, "cpu", {})
    env_kwargs = env_kwargs_for_policy(runner.policy.config)
    if args.regrasp_from != "marks":
        env_kwargs["regrasp_from"] = args.regrasp_from
    if args.arc_guard:
        env_kwargs["arc_guard"] = True
    chain_config = runner.policy.config
    run = lambda condition, seeds, name, desc: rollouts(  # noqa: E731
        runner, env_kwargs, chain_config, condition, seeds, args.batch_envs, args.work_dir / name, desc
    )

    calibration, calibration_s = run(
        "nominal", fresh_seeds(args.calibration_episodes), "calibration.pkl", "calibration"
    )
    closed = [log for log in calibration if log.success]
    thresholds = stage_thresholds(calibration, args.alpha, subtasks=args.scored)
    budgets = fit_stage_budgets(stage_durations(calibration), args.alpha, source="closed calibration sutures")
    thresholds.save(args.work_dir)
    budgets.save(args.work_dir)

    conditions, throws = {}, task_spec(TASK).throws
    scenarios = [s for s in task_spec(TASK).scenarios if s != "nominal"] if args.scenario_episodes else []
    for condition in ["nominal", *scenarios]:
        n = args.episodes if condition == "nominal" else args.scenario_episodes
        seeds = cells.condition_seeds(args.seed, TASK, condition, n)
        logs, seconds = run(condition, seeds, f"test.{condition}.pkl", "test")
        cell = cells.summarize_cell(logs, seconds, throws=throws)
        table = stage_alarm_table(logs, thresholds, budgets)
        table["scores_only"] = {
            k: v for k, v in stage_alarm_table(logs, thresholds, None).items() if k != "per_episode"
        }
        conditions[condition] = {
            "successes": cell["successes"],
            "success_interval": cell["success_interval"],
            "per_throw_on_marks_when_reached": [
                t["on_marks_when_reached"] for t in cell["per_throw"]["throws"]
            ],
            "seconds": round(seconds, 1),
            **table,
        }
    report = {
        "benchmark": "stage_gate",
        "chain": str(args.chain),
        "env": {k: v for k, v in env_kwargs.items() if k in ("regrasp_from", "arc_guard")},
        "alpha": args.alpha,
        "calibration": {
            "sutures": len(calibration),
            "closed": len(closed),
            "seconds": round(calibration_s, 1),
            "thresholds": thresholds.thresholds,
            "threshold_segments": thresholds.segments,
            "budgets": budgets.budgets,
            "budget_segments": budgets.segments,
        },
        "bars": {"failing_caught": CATCH_BAR, "successful_flagged": FALSE_ALARM_BAR},
        "conditions": conditions,
        "machine": machine(),
    }
    if args.plot is not None:
        figure(report, args.plot)
    emit(report, args.output)


if __name__ == "__main__":
    main()
