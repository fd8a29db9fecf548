"""One run of the board as a graph of stages (:mod:`.pipeline` has each stage): the rows trained or taken,
each cell evaluated or read back, the rows trained again from further seeds, then the board written.

Every stage is a Ray task (:mod:`.ray_stages`): on this machine by default, on a cluster with
``--ray_address``. A finished cell is never run again, so a rerun of the same command goes on where an
interrupted one stopped.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from lerobot_suture.leaderboard import cells
from lerobot_suture.leaderboard.board import plot, render
from lerobot_suture.leaderboard.pipeline import (
    GATED,
    PRESET_SEED,
    TASK_RECIPES,
    LeaderboardConfig,
    calibrate_stage,
    cell_path,
    evaluate_cell,
    finished_cell,
    row_name,
    train_policy,
)
from lerobot_suture.leaderboard.ray_stages import StageGraph
from lerobot_suture.pipelines.stages import StageTimings, calibrate_policy, record_recipe

logger = logging.getLogger(__name__)


def seeded_name(policy: str, seed: int) -> str:
    """The name of ``policy``'s row trained from the further seed ``seed`` (its cells' folder)."""
    return f"{policy}@seed{seed}"


def seeded_rows(cfg: LeaderboardConfig, board: dict) -> list[tuple[str, str]]:
    """The (task, policy) rows to train from ``cfg.train_seeds`` (see :class:`LeaderboardConfig`)."""
    if not cfg.train_seeds:
        return []
    if cfg.seeded_rows is not None:
        return [tuple(entry.split(":", 1)) for entry in cfg.seeded_rows]
    rows = []
    for task in cfg.tasks:
        if task == "insertion":
            rows += [(task, policy) for policy in cfg.policies]
        elif task in board.get("summary", {}):
            rows += [(task, p) for p in cells.best_rows(board["summary"][task]) if p in cfg.policies]
        else:
            logger.warning(
                "No seeded rows on %s yet: its two best rows are known once the board has the task. Run the board "
                "first, then again with --train_seeds.",
                task,
            )
    return rows


def submit_row(
    graph: StageGraph,
    cfg: LeaderboardConfig,
    task: str,
    name: str,
    policy_dir,
    overrides: dict,
    *after,
    shifts: list[str] | None = None,
) -> dict:
    """Every condition of ``task`` for row ``name`` (the board's shifts, or ``shifts``): the finished cells
    read back, a stage submitted for each other one; {condition: the cell, or its stage's key}."""
    row = {}
    for condition in cells.conditions(task, cfg.shifts if shifts is None else shifts):
        cell = finished_cell(cell_path(cfg, task, name, condition), overrides)
        if cell is None:
            cell = f"evaluate {task} {name} {condition}"
            graph.submit(
                cell,
                "cell",
                evaluate_cell,
                cfg,
                task,
                name,
                policy_dir,
                overrides,
                condition,
                *after,
                gpus=cfg.cell_gpus,
            )
        row[condition] = cell
    return row


def _submit_seeded_row(
    graph: StageGraph, cfg: LeaderboardConfig, task: str, policy: str, seed: int, dataset_root
) -> dict:
    """``policy`` trained again from ``seed`` (and calibrated, for a gated row), then evaluated on nominal and
    the task's scenarios."""
    name = seeded_name(policy, seed)
    policy_dir = graph.submit(
        f"train {task} {policy} seed {seed}", "train", train_policy, cfg, task, policy, dataset_root, seed,
        cpus=cfg.train_cpus,
    )  # fmt: skip
    after = []
    if policy in GATED:
        after.append(_submit_calibration(graph, cfg, task, policy, policy_dir, dataset_root, f" seed {seed}"))
    return submit_row(graph, cfg, task, name, policy_dir, {}, *after, shifts=[])


def _submit_calibration(
    graph: StageGraph,
    cfg: LeaderboardConfig,
    task: str,
    policy: str,
    policy_dir,
    dataset_root,
    suffix: str = "",
):
    """The calibration stage of a gated row's ``policy_dir`` on the task's validation data (its key:
    :func:`calibrate_stage` and ``suffix``)."""
    return graph.submit(
        calibrate_stage(task, policy) + suffix, "calibrate", calibrate_policy, policy_dir, dataset_root,
        cfg.device, cfg.toy, gpus=cfg.cell_gpus,
    )  # fmt: skip


def finished_row(row: dict, outputs: dict) -> dict | None:
    """A submitted row's cells, each read back or taken from its stage's output; None when a stage failed
    (the row waits for a rerun)."""
    done = {c: outputs.get(cell) if isinstance(cell, str) else cell for c, cell in row.items()}
    return done if all(isinstance(cell, dict) for cell in done.values()) else None


def add_stage_times(graph: StageGraph, seconds: dict[str, float], timings: StageTimings) -> None:
    """Record the wall time of every stage but the cells (a cell's time is its own ``seconds``)."""
    for key, s in seconds.items():
        if graph.kinds[key] != "cell":
            timings.add(key, s)


def raise_failures(failures: dict[str, str], output_dir) -> None:
    """Name every failed stage; what finished stays under ``output_dir`` for a rerun."""
    if failures:
        raise RuntimeError(
            f"{len(failures)} stage(s) failed: "
            + "; ".join(f"{k}: {v}" for k, v in sorted(failures.items()))
            + f". Every finished stage is kept under {output_dir}: rerun the same command to finish the rest."
        )


SIGNIFICANT_DIGITS = 6
"""Digits a float of a cell in ``leaderboard.json`` keeps: every figure a cell reports, in less room."""


def rounded(value, digits: int = SIGNIFICANT_DIGITS):
    """``value`` (JSON-like: dicts, lists, numbers) with every float rounded to ``digits`` significant digits."""
    if isinstance(value, float):
        return float(f"{value:.{digits}g}")
    if isinstance(value, dict):
        return {k: rounded(v, digits) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [rounded(v, digits) for v in value]
    return value


def board_cells(board: dict) -> list[dict]:
    """Every cell of ``board``: its rows' and its further training seeds' rows'."""
    rows = [row for by_task in board.get("tasks", {}).values() for row in by_task.values()]
    rows += [
        row
        for by_task in board.get("seeds", {}).values()
        for by_seed in by_task.values()
        for row in by_seed.values()
    ]
    return [cell for row in rows for cell in row.values()]


def _rollout_seconds(row: dict) -> float:
    """A row's evaluation time: its cells' rollout seconds, whichever runs they were made in."""
    return sum(cell["seconds"] for cell in row.values())


def run_leaderboard(cfg: LeaderboardConfig) -> dict:
    """Train or take every policy, evaluate every cell, write the board; returns it."""
    results = Path(cfg.results_dir)
    results.mkdir(parents=True, exist_ok=True)
    board_file = results / "leaderboard.json"
    board = json.loads(board_file.read_text()) if board_file.is_file() else {}
    for key in ("episodes", "seed"):  # rows run on other seeds or counts would not compare
        if board.get(key, getattr(cfg, key)) != getattr(cfg, key):
            raise ValueError(
                f"The board in {results} was run with --{key}={board[key]}; this run has "
                f"--{key}={getattr(cfg, key)}. Pass --{key}={board[key]} to join it, or another --results_dir."
            )
    board.update(episodes=cfg.episodes, seed=cfg.seed)
    if cfg.policy.path is None or "shifts" not in board:  # a joining row keeps the board's conditions
        board["shifts"] = cfg.shifts
    board.setdefault("tasks", {})
    timings = StageTimings(cfg.output_dir / "timings.json")
    graph = StageGraph(cfg.ray_address)
    submitted: dict[tuple[str, str], dict] = {}
    if cfg.policy.path is not None:  # a user's checkpoint joins the board
        # config.json names its type: read it there, before any policy plugin is registered
        policy_type = json.loads((Path(cfg.policy.path) / "config.json").read_text())["type"]
        name = cfg.policy_name or row_name(policy_type, cfg.policy.overrides)
        policy_dir = Path(cfg.policy.path).resolve()
        for task in cfg.tasks:
            submitted[task, name] = submit_row(graph, cfg, task, name, policy_dir, cfg.policy.overrides)
    seeded = seeded_rows(cfg, board)
    seeded_submitted: dict[tuple[str, str, int], dict] = {}
    if cfg.policy.path is None:
        for task in cfg.tasks:
            dataset_root = None
            if any((task, p) not in cfg.taken for p in cfg.policies) or any(t == task for t, _ in seeded):
                root = cfg.output_dir / "data" / task
                dataset_root = graph.submit(
                    f"record {task}", "record", record_recipe, TASK_RECIPES[task][0], root, cfg.toy
                )
            for policy in cfg.policies:
                policy_dir = cfg.taken.get((task, policy))
                if policy_dir is None:
                    policy_dir = graph.submit(
                        f"train {task} {policy}", "train", train_policy, cfg, task, policy, dataset_root,
                        cpus=cfg.train_cpus,
                    )  # fmt: skip
                after = []
                if policy in GATED and dataset_root is not None:
                    after.append(_submit_calibration(graph, cfg, task, policy, policy_dir, dataset_root))
                submitted[task, policy] = submit_row(graph, cfg, task, policy, policy_dir, {}, *after)
            for policy in (p for t, p in seeded if t == task):
                for seed in cfg.train_seeds:
                    seeded_submitted[task, policy, seed] = _submit_seeded_row(
                        graph, cfg, task, policy, seed, dataset_root
                    )
    outputs, seconds, failures = graph.run("leaderboard")
    add_stage_times(graph, seconds, timings)
    for (task, name), row in submitted.items():
        if (done := finished_row(row, outputs)) is not None:
            board["tasks"].setdefault(task, {})[name] = done
            timings.seconds[f"evaluate {task} {name}"] = _rollout_seconds(done)
    for (task, policy, seed), row in seeded_submitted.items():
        if (done := finished_row(row, outputs)) is not None:
            board.setdefault("seeds", {}).setdefault(task, {}).setdefault(policy, {})[str(seed)] = done
            timings.seconds[f"evaluate {task} {seeded_name(policy, seed)}"] = _rollout_seconds(done)
    if board.get("seeds"):
        board["seed_spread"] = cells.seed_spreads(board, PRESET_SEED)
    board["summary"] = {
        task: {
            name: cells.row_summary(row, cells.conditions(task, board["shifts"]))
            for name, row in rows.items()
        }
        for task, rows in board["tasks"].items()
    }
    # The rows already on the board keep their times; this run's stages add or update theirs.
    board["timings"] = {**board.get("timings", {}), **{k: round(v, 1) for k, v in timings.seconds.items()}}
    for key in ("tasks", "seeds"):  # the cells; the summary keeps its floats as computed
        if key in board:
            board[key] = rounded(board[key])
    for cell in board_cells(board):
        if isinstance(cell.get("per_episode"), list):
            cell["per_episode"] = cells.packed_episodes(cell["per_episode"])
    board_file.write_text(json.dumps(board, separators=(",", ":")))
    (results / "leaderboard.md").write_text(render(board))
    plot(board, results / "leaderboard.png")
    raise_failures(failures, cfg.output_dir)
    return board
