"""What a chained policy needs from the surgeon to close running sutures: a time budget per stage, enforced.

The chain runs the leaderboard's nominal test seeds of the running suture, the CBF on, one suture at a time. A gate
per stage (``runtime.gates.StageGates``) gives each subtask a time budget: the conformal quantile (at ``--alpha``)
of that subtask's durations in the recording's training sutures (``--dataset``; ``datasets.segment.subtask_durations``,
``safety.ood.stage_gate.fit_stage_budgets``), times ``--slack``; or, with ``--stage-dir``, the budgets and the
score thresholds that ``benchmarks/stage_gate.py`` fitted on the chain's own closed sutures (a segment is flagged too
when its policy's score passes its subtask's threshold). A segment that outlasts its budget is flagged and
the scripted surgeon (``expert_per_subtask``) takes that subtask over and hands back for the next, so a stage that
stalls (an extract that closed beside the needle and holds its jaw shut) costs one intervention instead of the
suture. The chain must read the subtask from the env (``lerobot-suture chain --subtask_from_env=true``): a
hand-back resets the policy, and the env's reading carries on through the surgeon's steps. STITCH 2.0 closes every
wound when up to two interventions are allowed; this counts ours.

Prints one JSON object: the budgets, per suture the outcome, the throws on the marks and each intervention (the
step, and the subtask the flag fell in), and the sutures closed with at most k interventions; ``--plot`` draws that
curve::

    .venv/bin/python benchmarks/chain_interventions.py --policy-path CHAIN (--dataset DIR | --stage-dir DIR) \
        [--episodes 50] [--regrasp-from release] [--arc-guard]
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import time
from collections import Counter
from pathlib import Path

from _report import emit, machine

NEEDS = "a chain written with --subtask_from_env=true (--policy-path), and --dataset DIR or --stage-dir DIR"
TASK = "running_suture"


def interventions(log) -> list[dict]:
    """Each takeover of the episode ``log``: the step, and the subtask the flag fell in."""
    from lerobot_suture.runtime.takeover import Actor

    taken = [step for step, _, to, _ in log.handovers if to is Actor.SURGEON]
    return [{"step": step, "subtask": log.steps[step].subtask} for step in taken]


def closed_within(episodes: list[dict], most: int) -> list[int]:
    """How many sutures closed with at most k interventions, for k = 0..``most``."""
    return [sum(ep["success"] and len(ep["interventions"]) <= k for ep in episodes) for k in range(most + 1)]


def figure(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lerobot_suture.plotting import save_figure

    closed = report["closed_within"]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.step(range(len(closed)), closed, where="post")
    ax.set_xlabel("interventions allowed per suture")
    ax.set_ylabel(f"sutures closed (of {report['episodes']})")
    ax.set_ylim(0, report["episodes"])
    ax.axvline(2, color="grey", linestyle=":", label="STITCH 2.0: every wound within 2")
    ax.legend(loc="lower right")
    ax.set_title("A chained policy with a gate per stage, the surgeon taking flagged stages over")
    save_figure(fig, path)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy-path", type=Path, required=True)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--dataset", type=Path, help="the recording whose training sutures set the budgets")
    source.add_argument(
        "--stage-dir",
        type=Path,
        help="stage_calibration.json and stage_budgets.json (benchmarks/stage_gate.py)",
    )
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=7_000_000, help="the leaderboard's base of test seeds")
    parser.add_argument("--alpha", type=float, default=0.01)
    parser.add_argument("--slack", type=float, default=1.0, help="each budget times this (>= 1)")
    parser.add_argument("--output", type=Path)
    parser.add_argument("--plot", type=Path)
    parser.add_argument("--regrasp-from", choices=("marks", "release"), default="marks")
    parser.add_argument("--arc-guard", action="store_true", help="hold the needle in tissue to its arc")
    args = parser.parse_args()
    if not args.slack >= 1.0:
        parser.error(f"--slack must be >= 1 (a budget shorter than the expert's). Got {args.slack}.")

    from lerobot_suture.datasets.segment import subtask_durations
    from lerobot_suture.leaderboard import cells
    from lerobot_suture.runtime.gates import ReportingGates, SilentGates, StageGates
    from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy
    from lerobot_suture.runtime.rollout import make_scenario_env, rollout_seeds
    from lerobot_suture.safety.cbf_config import CBFConfig
    from lerobot_suture.safety.ood.stage_gate import StageBudgets, StageThresholds, fit_stage_budgets
    from lerobot_suture.sim.tasks import task_spec

    if args.stage_dir is not None:
        fitted, thresholds = StageBudgets.load(args.stage_dir), StageThresholds.load(args.stage_dir)
    else:
        fitted = fit_stage_budgets(subtask_durations(args.dataset), args.alpha, source=str(args.dataset))
        thresholds = None
    budgets = dataclasses.replace(
        fitted, budgets={stage: int(round(args.slack * steps)) for stage, steps in fitted.budgets.items()}
    )
    runner = PolicyRunner.from_pretrained(args.policy_path, GateMode.REPORT, "cpu", {})
    env_kwargs = env_kwargs_for_policy(runner.policy.config)
    if args.regrasp_from != "marks":
        env_kwargs["regrasp_from"] = args.regrasp_from
    if args.arc_guard:
        env_kwargs["arc_guard"] = True
    if not env_kwargs.get("subtask"):
        raise SystemExit(
            f"{args.policy_path} runs its own rules, which a hand-back resets to the first throw: write the chain "
            "with `lerobot-suture chain --subtask_from_env=true`."
        )
    seeds = cells.condition_seeds(args.seed, TASK, "nominal", args.episodes)
    make_env = functools.partial(
        make_scenario_env, {**env_kwargs, "task": TASK}, "nominal", CBFConfig(enabled=True)
    )
    start = time.perf_counter()
    logs = rollout_seeds(
        make_env,
        runner,
        seeds,
        batch_envs=1,  # a hand-back resets the policy
        surgeon="expert_per_subtask",
        desc="sutures",
        gates=StageGates(
            SilentGates() if thresholds is None else ReportingGates(runner.policy),
            thresholds,
            rules=getattr(runner.policy.config, "rules", None),
            budgets=budgets,
        ),
    )
    seconds = time.perf_counter() - start
    episodes = [
        {
            "seed": log.seed,
            "success": log.success,
            "steps": len(log.steps),
            "throws_on_marks": sum(bool(t.get("on_marks")) for t in log.throw_results),
            "interventions": interventions(log),
        }
        for log in logs
    ]
    taken = Counter(i["subtask"] for ep in episodes for i in ep["interventions"])
    summary = cells.summarize_cell(logs, seconds, throws=task_spec(TASK).throws)
    report = {
        "benchmark": "chain_interventions",
        "policy": str(args.policy_path),
        "budgets": {
            **budgets.budgets,
            "slack": args.slack,
            "alpha": budgets.alpha,
            "segments": budgets.segments,
        },
        "thresholds": None if thresholds is None else {**thresholds.thresholds, "alpha": thresholds.alpha},
        "env": {k: v for k, v in env_kwargs.items() if k in ("regrasp_from", "arc_guard")},
        "episodes": len(episodes),
        "successes": summary["successes"],
        "success_interval": summary["success_interval"],
        "per_throw": summary.get("per_throw"),
        "interventions_per_subtask": dict(taken),
        "interventions_per_suture_mean": sum(len(ep["interventions"]) for ep in episodes)
        / max(len(episodes), 1),
        "closed_within": closed_within(episodes, 12),
        "per_episode": episodes,
        "seconds": round(seconds, 1),
        "machine": machine(),
    }
    if args.plot is not None:
        figure(report, args.plot)
    emit(report, args.output)


if __name__ == "__main__":
    main()
