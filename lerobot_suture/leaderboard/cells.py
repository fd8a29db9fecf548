"""The leaderboard's cells: one policy on one task under one condition, and its summary.

A cell is ``episodes`` closed-loop episodes on the cell's own test seeds (the same seeds for every policy),
with the CBF filtering every action at the env step and the policy's O.O.D. gate, when it has one,
reporting (it never stops a run: the success rate is the policy's own). A condition is ``nominal``, one of
the task's perturbation scenarios, or a distribution shift (``shift:NAME@MAGNITUDE``) in the nominal scene.

Its summary holds the success rate with its 95% Wilson interval, what the gate did (episodes with an
O.O.D. decision: false alarms on ``nominal``, detections under a perturbation) and what the CBF did
(steps it was active on, the share of those it changed the action, episodes whose needle tip left the safe
set at any physics step, the smallest barrier value). A task of several throws (the running suture) adds the
outcome of each throw (:func:`~lerobot_suture.experiments.per_throw.per_throw_table`): where a policy gets
in a suture that none finishes.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Sequence

import numpy as np

from lerobot_suture.experiments.metrics import wilson_interval
from lerobot_suture.experiments.per_throw import per_throw_table
from lerobot_suture.runtime.rollout import EpisodeLog, make_scenario_env, rollout_seeds
from lerobot_suture.runtime.seeds import episode_seeds
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.sim.shifts import SHIFTS, Shift
from lerobot_suture.sim.tasks import TASK_NAMES, task_spec

SHIFT_PREFIX = "shift:"
SHIFT_SEED_GROUP = 100
"""Test-seed group of the first shift condition (the scenarios take groups 0 onwards)."""


def conditions(task: str, shifts: Sequence[str]) -> list[str]:
    """A task's conditions: its scenarios (``nominal`` first), then ``shift:LABEL`` for each shift."""
    spec = task_spec(task)
    return list(spec.scenarios) + [SHIFT_PREFIX + Shift.parse(s).label for s in shifts]


def condition_seeds(base: int, task: str, condition: str, n: int) -> list[int]:
    """The test seeds of one condition: the same for every policy, disjoint across tasks and conditions but
    shared by the magnitudes of one shift (the same scenes, shifted more: paired, as the detector benchmark
    runs them)."""
    spec = task_spec(task)
    if condition.startswith(SHIFT_PREFIX):
        group = SHIFT_SEED_GROUP + _shift_index(condition)
    else:
        group = spec.scenarios.index(condition)
    return episode_seeds(base + TASK_NAMES.index(task) * 1000 * 10_000, group, n)


def condition_shift(condition: str) -> Shift | None:
    """The shift of a ``shift:NAME@MAGNITUDE`` condition; None for a scenario."""
    return Shift.parse(condition.removeprefix(SHIFT_PREFIX)) if condition.startswith(SHIFT_PREFIX) else None


def _shift_index(condition: str) -> int:
    return SHIFTS.index(condition_shift(condition).name)


def cell_episodes(
    runner,
    env_kwargs: dict,
    task: str,
    condition: str,
    seeds: Sequence[int],
    batch_envs: int,
    workers: int = 1,
    gates=None,
) -> tuple[list[EpisodeLog], float]:
    """Roll ``runner`` out on ``seeds`` under ``condition`` of ``task`` (``batch_envs`` in lockstep, in
    ``workers`` processes), the CBF on; returns the episodes and their wall time (s). ``gates``: the gates to log
    (``runtime.gates``; one worker), else the policy's own."""
    shift = condition_shift(condition)
    scenario = condition if shift is None else "nominal"
    kwargs = {**env_kwargs, "task": task}
    start = time.perf_counter()
    logs = rollout_seeds(
        functools.partial(make_scenario_env, kwargs, scenario, CBFConfig(enabled=True), True, shift),
        runner,
        seeds,
        batch_envs,
        desc=f"{task}, {condition}",
        workers=workers,
        gates=gates,
    )
    return logs, time.perf_counter() - start


def packed_episodes(rows: Sequence[Sequence]) -> dict:
    """A cell's ``per_episode`` rows (seed, success, steps, first alarm step or None) as columns, in about a fifth
    of the room on the board: the first seed (and every seed only where they do not run on, as a cell's do), each
    success as ``1`` or ``0``, the steps, and the alarms by row. :func:`unpacked_episodes` gives the rows back."""
    seeds = [int(row[0]) for row in rows]
    packed = {
        "first_seed": seeds[0] if seeds else None,
        "success": "".join("1" if row[1] else "0" for row in rows),
        "steps": [int(row[2]) for row in rows],
        "first_alarm": {str(i): int(row[3]) for i, row in enumerate(rows) if row[3] is not None},
    }
    if seeds and seeds != list(range(seeds[0], seeds[0] + len(seeds))):
        packed["seeds"] = seeds
    return packed


def unpacked_episodes(packed: dict) -> list[list]:
    """The rows :func:`packed_episodes` packed."""
    n = len(packed["steps"])
    seeds = packed.get("seeds") or [packed["first_seed"] + i for i in range(n)]
    alarms = packed["first_alarm"]
    return [[seeds[i], packed["success"][i] == "1", packed["steps"][i], alarms.get(str(i))] for i in range(n)]


def summarize_cell(logs: Sequence[EpisodeLog], seconds: float, throws: int = 1) -> dict:
    """A cell's figures from its episodes (see the module docstring); with ``throws`` > 1 (the task's
    ``TaskSpec.throws``) also each throw's outcome, as ``per_throw``."""
    n = len(logs)
    successes = sum(log.success for log in logs)
    low, high = wilson_interval(successes, n)
    has_gate = any(not math.isnan(s.score) for log in logs for s in log.steps)
    flagged = [log for log in logs if log.first_alarm_step is not None]
    active = [s for log in logs for s in log.steps if s.cbf_active]
    h_mins = [log.h_min_physics for log in logs if not math.isnan(log.h_min_physics)]
    cell = {
        "episodes": n,
        "successes": int(successes),
        "success_rate": successes / n if n else math.nan,
        "success_interval": [low, high],
        "gate": {
            "flagged": len(flagged),
            "flagged_rate": len(flagged) / n if n else math.nan,
            "flagged_failures": sum(not log.success for log in flagged),
            "failures": n - int(successes),
        }
        if has_gate
        else None,
        "cbf": {
            "active_steps": len(active),
            "intervention_rate": float(np.mean([s.cbf_intervened for s in active])) if active else 0.0,
            "violating_episodes": int(sum(h < 0 for h in h_mins)),
            "h_min": float(min(h_mins)) if h_mins else None,
        },
        "mean_steps": float(np.mean([len(log.steps) for log in logs])) if logs else math.nan,
        "seconds": round(seconds, 1),
        "per_episode": [[log.seed, bool(log.success), len(log.steps), log.first_alarm_step] for log in logs],
    }
    if throws > 1:
        cell["per_throw"] = per_throw_table(logs, throws)
    return cell


def throws_on_marks_mean(cell: dict) -> float | None:
    """Throws on the marks per episode of a cell, on average (None for a task of one throw or none)."""
    table = cell.get("per_throw")
    if table is None or not table["episodes"]:
        return None
    return sum(t["on_marks"]["count"] for t in table["throws"]) / table["episodes"]


def has_throws(rows: dict) -> bool:
    """Whether some cell of a task's ``rows`` holds each throw's outcome (a task of several throws)."""
    return any("per_throw" in cell for row in rows.values() for cell in row.values())


def task_conditions(rows: dict) -> list[str]:
    """Every condition some row of a task holds, in the order they were run."""
    return list(dict.fromkeys(c for row in rows.values() for c in row))


def row_summary(row: dict, conditions: Sequence[str] | None = None) -> dict:
    """One policy's row in a few figures: nominal success, the mean success over the perturbation scenarios
    and over the shifts, the gate's false alarms on nominal (None without a gate), and on a task of several
    throws the throws on the marks per nominal episode (otherwise None).

    ``conditions`` are the board's conditions of the task (default: the row's own); a mean over a group the
    row holds only part of is None, as it would not compare with the other rows' means, and cells beyond
    them (a joining row's further shifts) count in no mean."""
    conditions = list(row) if conditions is None else list(conditions)
    nominal = row.get("nominal")

    def mean(group: list[str]) -> float | None:
        if not group or any(c not in row for c in group):
            return None
        return float(np.mean([row[c]["success_rate"] for c in group]))

    return {
        "nominal_success": nominal["success_rate"] if nominal else None,
        "scenario_success_mean": mean(
            [c for c in conditions if c != "nominal" and not c.startswith(SHIFT_PREFIX)]
        ),
        "shift_success_mean": mean([c for c in conditions if c.startswith(SHIFT_PREFIX)]),
        "nominal_false_alarms": nominal["gate"]["flagged_rate"] if nominal and nominal["gate"] else None,
        "nominal_throws_on_marks": throws_on_marks_mean(nominal) if nominal else None,
        "cbf_violating_episodes": sum(row[c]["cbf"]["violating_episodes"] for c in conditions if c in row),
        "episodes": sum(row[c]["episodes"] for c in conditions if c in row),
    }


def seed_spread(cells_by_seed: dict[int, dict]) -> dict:
    """One condition of a row over its training seeds: the mean success rate with its range over the seeds,
    beside each seed's rate and Wilson interval."""
    seeds = sorted(cells_by_seed)
    rates = [cells_by_seed[s]["success_rate"] for s in seeds]
    return {
        "seeds": seeds,
        "success_mean": float(np.mean(rates)),
        "success_range": [float(min(rates)), float(max(rates))],
        "per_seed": {
            str(s): {"success_rate": c["success_rate"], "success_interval": c["success_interval"]}
            for s, c in ((s, cells_by_seed[s]) for s in seeds)
        },
    }


def best_rows(summary: dict, n: int = 2) -> list[str]:
    """The ``n`` rows of a task's summary with the highest nominal success, ties broken by the mean over the
    scenarios, then by name (a missing figure counts as 0)."""

    def key(name: str) -> tuple:
        s = summary[name]
        return (-(s["nominal_success"] or 0.0), -(s["scenario_success_mean"] or 0.0), name)

    return sorted(summary, key=key)[:n]


def seed_spreads(board: dict, preset_seed: int) -> dict:
    """{task: {policy: {condition: :func:`seed_spread`}}} for every row of ``board["seeds"]``: the board's own
    row (trained from ``preset_seed``) and its further seeds, on the conditions every one of them holds."""
    spreads: dict = {}
    for task, policies in board.get("seeds", {}).items():
        for policy, by_seed in policies.items():
            main = board["tasks"].get(task, {}).get(policy)
            if main is None:
                continue
            rows = {preset_seed: main, **{int(s): row for s, row in by_seed.items()}}
            shared = [c for c in main if all(c in row for row in rows.values())]
            spreads.setdefault(task, {})[policy] = {
                c: seed_spread({s: row[c] for s, row in rows.items()}) for c in shared
            }
    return spreads
