"""The leaderboard's time on a cluster, projected from the stage times its board measured on 2 cores.

Every stage of the board (record, train, calibrate, and each cell) becomes a task of the graph Ray runs
(:mod:`lerobot_suture.leaderboard.pipeline`): a training waits for its task's recording, a calibration for
the ensemble's training, a cell for its policy (and the ensemble's cells for the calibration).
:func:`lerobot_suture.leaderboard.schedule.makespan` then places the tasks on ``--machines`` nodes of
``--cpus`` cores the way Ray does (a task starts once its inputs exist and a node has its cores).

The inputs are the board's measured times: ``timings`` for record, train and calibrate (a training on
``--train-cpus`` cores), and each cell's own ``seconds``. The cells were measured in one process on 2 cores;
on Ray a cell holds one core, so its time is scaled by the one-core slowdown measured by
``eval_throughput.json`` (8 envs in one process on 2 threads, against each of 2 one-thread workers). A
stage the board lacks (a row that joined with its checkpoint, not trained by the board) takes the mean of
the same stage on the other tasks, and is listed under ``estimated``; a row the board lacks on a task takes
its cells' times from the ensemble's row there.

    .venv/bin/python benchmarks/leaderboard_projection.py [--machines 1 16] [--output FILE]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from statistics import mean

from _report import emit, machine

from lerobot_suture.leaderboard.cells import conditions
from lerobot_suture.leaderboard.pipeline import GATED, POLICIES, calibrate_stage
from lerobot_suture.leaderboard.schedule import Stage, makespan

ROOT = Path(__file__).resolve().parents[1]


def one_core_slowdown(throughput: dict) -> float:
    """A cell's time on one core over its time in one process on 2 threads (the board's runs)."""
    configs = {(c["batch_envs"], c["workers"]): c for c in throughput["configurations"]}
    two_threads = configs[(8, 1)]["episodes_per_min"]
    one_thread = configs[(8, 2)]["episodes_per_min"] / 2
    return two_threads / one_thread


def board_graph(board: dict, slowdown: float, train_cpus: int) -> tuple[list[Stage], list[str]]:
    """The board's stages as a graph, and the stages whose time was estimated."""
    timings, stages, estimated = board["timings"], [], []

    def seconds(stage: str) -> float:
        if stage in timings:
            return timings[stage]
        kind, task, *row = stage.split(" ")
        # The same stage on the other tasks; else any stage of its kind on its task.
        same = [s for key, s in timings.items() if key.split(" ")[0] == kind and key.split(" ")[2:] == row]
        same = same or [s for key, s in timings.items() if key.split(" ")[:2] == [kind, task]]
        estimated.append(stage)
        return mean(same)

    for task, rows in board["tasks"].items():
        record = f"record {task}"
        stages.append(Stage(record, seconds(record)))
        for policy in POLICIES:
            row = rows.get(policy)
            if row is None:
                row = rows["ensemble_diffusion"]
                estimated.append(f"evaluate {task} {policy}")
            train = f"train {task} {policy}"
            stages.append(Stage(train, seconds(train), cpus=train_cpus, after=(record,)))
            before = (train,)
            if policy in GATED:
                calibrate = calibrate_stage(task, policy)
                stages.append(Stage(calibrate, seconds(calibrate), after=(train,)))
                before = (train, calibrate)
            for condition in conditions(task, board["shifts"]):  # the cells a run of the table makes
                seconds_one_core = row[condition]["seconds"] * slowdown
                stages.append(Stage(f"evaluate {task} {policy} {condition}", seconds_one_core, after=before))
    return stages, estimated


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--board", type=Path, default=ROOT / "docs/results/leaderboard/leaderboard.json")
    parser.add_argument(
        "--throughput", type=Path, default=ROOT / "docs/results/benchmarks/eval_throughput.json"
    )
    parser.add_argument("--machines", type=int, nargs="+", default=[1, 16])
    parser.add_argument("--cpus", type=int, default=2, help="cores per machine")
    parser.add_argument("--train-cpus", type=int, default=2, help="cores a training holds")
    parser.add_argument("--output", type=Path, default=None)
    args = parser.parse_args()

    board = json.loads(args.board.read_text())
    slowdown = one_core_slowdown(json.loads(args.throughput.read_text()))
    graph, estimated = board_graph(board, slowdown, args.train_cpus)
    by_kind: dict[str, float] = {}
    for stage in graph:
        kind = stage.key.split(" ", 1)[0]
        by_kind[kind] = by_kind.get(kind, 0.0) + stage.seconds * stage.cpus / 3600
    projected = {str(m): round(makespan(graph, m, args.cpus) / 3600, 2) for m in args.machines}
    emit(
        {
            "benchmark": "leaderboard_projection",
            "board": str(args.board.relative_to(ROOT) if args.board.is_relative_to(ROOT) else args.board),
            "stages": len(graph),
            "cores_per_machine": args.cpus,
            "train_cpus": args.train_cpus,
            "cell_one_core_slowdown": round(slowdown, 3),
            "core_hours_by_stage": {k: round(v, 2) for k, v in by_kind.items()},
            "longest_chain_hours": round(
                makespan(graph, len(graph), max(args.cpus, args.train_cpus)) / 3600, 2
            ),
            "projected_hours_by_machines": projected,
            "estimated": estimated,
            "machine": machine(),
        },
        args.output,
    )


if __name__ == "__main__":
    main()
