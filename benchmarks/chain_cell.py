"""A running-suture chain of trained policies, one per subtask where given, on the leaderboard's nominal test
seeds of the running suture: the board's nominal cell, throw by throw.

``lerobot-suture chain`` writes the chain (``--policy`` for every subtask not given its own, ``--insert``,
``--extract``, ``--lay-down``, ``--pick-up``); the cell is evaluated as ``task_levers.py`` evaluates a lever
(the CBF on, the gate only reporting). Each policy is a ``pretrained_model`` directory of ``lerobot-train``; a
policy trained on relative actions composes them in its own processors, so policies of either kind mix::

    .venv/bin/python benchmarks/chain_cell.py --policy DIR --extract DIR --work-dir outputs/chain_cell/NAME

A policy that reads the planned regrasp gets it from the env; ``--regrasp-from release`` plans it from where the
jaw let go of the needle instead of through the marks (``sim.regrasp_target``); ``--arc-guard`` holds a needle
in tissue to its arc (``safety.arc_guard``); ``--scripted-regrasp`` scripts the extract's regrasp (a servo on the
measured pose and the planned regrasp, ``sim.regrasp_servo``), the extract policy pulling once the jaw holds the
tip; ``--scripted-pull`` scripts the pull too (a turn about the needle's centre estimated from the jaw's pose at the
hold, ``sim.pull_servo``); ``--scripted-pick-up`` scripts the pick-up (a servo planned from where the jaw last held
the needle and the marks' height, ``sim.pickup_servo``). ``--task extraction --scenarios`` runs the chain on the extraction task's board cells
instead, every scenario included. The chain and the finished cells are kept in ``--work-dir``: a rerun reads them
back.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from _report import emit, machine
from task_levers import evaluate

NEEDS = "trained policies for the running suture's subtasks (--policy, and --insert / --extract / ... DIR)"
SUBTASK_FLAGS = ("insert", "extract", "lay_down", "pick_up")


def main() -> None:
    from lerobot_policy_suture_chain.assemble import ChainCommandConfig, write_chain

    from lerobot_suture.sim.tasks import task_spec

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", type=Path, help="the policy of every subtask not given its own")
    for name in SUBTASK_FLAGS:
        parser.add_argument(f"--{name.replace('_', '-')}", type=Path, help=f"the {name} subtask's own policy")
    parser.add_argument("--episodes", type=int, default=50, help="test episodes")
    parser.add_argument("--seed", type=int, default=7_000_000, help="the leaderboard's base of test seeds")
    parser.add_argument("--batch-envs", type=int, default=8)
    parser.add_argument("--work-dir", type=Path, required=True, help="the chain and its cell (rerun: resume)")
    parser.add_argument("--output", type=Path)
    parser.add_argument(
        "--regrasp-from",
        choices=("marks", "release"),
        default="marks",
        help="where the env plans the regrasp",
    )
    parser.add_argument(
        "--arc-guard", action="store_true", help="hold the needle in tissue to its arc (safety.arc_guard)"
    )
    parser.add_argument(
        "--scripted-regrasp", action="store_true", help="script the extract's regrasp (sim.regrasp_servo)"
    )
    parser.add_argument(
        "--scripted-pull", action="store_true", help="script the extract's pull too (sim.pull_servo)"
    )
    parser.add_argument(
        "--scripted-pick-up", action="store_true", help="script the pick-up (sim.pickup_servo)"
    )
    parser.add_argument("--task", choices=("running_suture", "extraction"), default="running_suture")
    parser.add_argument("--scenarios", action="store_true", help="the task's perturbation scenarios too")
    args = parser.parse_args()

    policies = {"policy": args.policy, **{name: getattr(args, name) for name in SUBTASK_FLAGS}}
    chain_dir = args.work_dir / "chain"
    if not (chain_dir / "config.json").is_file():  # the config refuses a subtask without a policy
        write_chain(
            ChainCommandConfig(
                output_dir=chain_dir,
                scripted_regrasp=args.scripted_regrasp,
                scripted_pull=args.scripted_pull,
                scripted_pick_up=args.scripted_pick_up,
                **policies,
            )
        )
    overrides = {} if args.regrasp_from == "marks" else {"regrasp_from": args.regrasp_from}
    if args.arc_guard:
        overrides["arc_guard"] = True
    conditions = task_spec(args.task).scenarios if args.scenarios else ("nominal",)
    cells, task_suffix = {}, "" if args.task == "running_suture" else f".{args.task}"
    for condition in conditions:
        cell_path = (
            args.work_dir / f"cell{task_suffix}{'' if condition == 'nominal' else '.' + condition}.json"
        )
        if cell_path.is_file():
            cells[condition] = json.loads(cell_path.read_text())
        else:
            start = time.perf_counter()
            print(f"evaluating the chain on {args.episodes} test episodes, {condition} ...", flush=True)
            cell = evaluate(
                args.task, chain_dir, args.episodes, args.seed, args.batch_envs, condition, overrides
            )
            cell["evaluation_s"] = round(time.perf_counter() - start, 1)
            cell_path.write_text(json.dumps(cell))
            cells[condition] = cell
        print(f"{condition}: {cells[condition]['successes']}/{cells[condition]['episodes']}", flush=True)
    report = {
        "task": args.task,
        "policies": {name: str(path) for name, path in policies.items() if path is not None},
        "chain": str(chain_dir),
        "regrasp_from": args.regrasp_from,
        "arc_guard": args.arc_guard,
        "scripted_regrasp": args.scripted_regrasp,
        "scripted_pull": args.scripted_pull,
        "scripted_pick_up": args.scripted_pick_up,
        "nominal": cells["nominal"],
        **({"scenarios": {c: cell for c, cell in cells.items() if c != "nominal"}} if len(cells) > 1 else {}),
        "machine": machine(),
    }
    emit(report, args.output)


if __name__ == "__main__":
    main()
