"""What a gate per stage would have flagged on running sutures, as pure functions of their episode logs.

The logs come from rollouts with :class:`~lerobot_suture.runtime.gates.StageGates` recording only (no threshold,
no budget), so each step names the subtask the high level read and each prediction its score. A segment is a run
of steps in one subtask. The budgets are fitted on the successful sutures' segment lengths (control steps), the
thresholds on their segments' largest scores (``runtime.calibration.stage_thresholds``), FAIL-Detect's
convention. :func:`first_flag` replays a suture through :class:`~lerobot_suture.safety.ood.stage_gate.StageGate`
step by step, as the gate would have run: the first flag, its step, its subtask and its cause (``score`` or
``budget``). A failing suture is *caught* when the flag falls before its failing throw ends: the step its insert
drove the needle through off the marks, else the episode's last step (an unfinished insert, a throw not
extracted).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from typing import TYPE_CHECKING

from lerobot_suture.experiments.metrics import wilson_interval
from lerobot_suture.safety.ood.stage_gate import StageBudgets, StageGate, StageThresholds, segment_runs

if TYPE_CHECKING:
    from lerobot_suture.runtime.rollout import EpisodeLog


def stage_durations(logs: Sequence[EpisodeLog]) -> dict[str, list[int]]:
    """Each subtask's segment lengths (control steps) in the episodes that succeeded; a segment cut by the
    episode's end is left out (its length is not a stage's)."""
    durations: dict[str, list[int]] = {}
    for log in logs:
        if not log.success:
            continue
        runs = segment_runs([s.subtask for s in log.steps])
        for subtask, _, start, stop in runs[:-1]:
            if subtask:
                durations.setdefault(subtask, []).append(stop - start)
    return durations


def first_flag(
    log: EpisodeLog, thresholds: StageThresholds | None, budgets: StageBudgets | None
) -> dict | None:
    """The first flag a gate per stage would have raised on ``log`` (see the module docstring), or None:
    ``{"step", "subtask", "throw", "cause"}``."""
    gate = StageGate(thresholds, budgets)
    for subtask, throw, start, stop in segment_runs([s.subtask for s in log.steps]):
        gate.enter(subtask, throw)
        for step in range(start, stop):
            entry = log.steps[step]
            cause = "budget" if gate.tick() else None
            if cause is None and entry.new_prediction and entry.consulted and gate.update(entry.score):
                cause = "score"
            if cause is not None:
                return {"step": step, "subtask": subtask, "throw": throw + 1, "cause": cause}
    return None


def failing_throw_end(log: EpisodeLog) -> int:
    """The step (0-based, of ``log.steps``) at which a failed suture's failing throw ended: the step whose action
    drove its last throw through off the marks, else the episode's last step."""
    results = log.throw_results
    if results and not results[-1]["on_marks"]:
        return int(results[-1]["over_step"]) - 1  # the env counts its steps from 1
    return len(log.steps) - 1


def _rate(count: int, n: int) -> dict:
    return {
        "count": count,
        "of": n,
        "rate": count / n if n else None,
        "wilson_95": list(wilson_interval(count, n)),
    }


def stage_alarm_table(
    logs: Sequence[EpisodeLog], thresholds: StageThresholds | None, budgets: StageBudgets | None
) -> dict:
    """Over ``logs`` (one condition): the failing sutures flagged before their failing throw ended, the
    successful ones flagged at all, each with its 95% Wilson interval; the flags' causes and subtasks, and how many
    steps before the failing throw's end the catches came (median)."""
    flags = [first_flag(log, thresholds, budgets) for log in logs]
    failing = [(log, f) for log, f in zip(logs, flags, strict=True) if not log.success]
    caught = [(log, f) for log, f in failing if f is not None and f["step"] < failing_throw_end(log)]
    false_alarms = [f for log, f in zip(logs, flags, strict=True) if log.success and f is not None]
    leads = sorted(failing_throw_end(log) - f["step"] for log, f in caught)
    return {
        "episodes": len(logs),
        "failing_caught": _rate(len(caught), len(failing)),
        "successful_flagged": _rate(len(false_alarms), len(logs) - len(failing)),
        "caught_by": dict(Counter(f["cause"] for _, f in caught)),
        "caught_in": dict(Counter(f"{f['subtask']} {f['throw']}" for _, f in caught)),
        "false_alarms_in": dict(Counter(f"{f['subtask']} {f['throw']} ({f['cause']})" for f in false_alarms)),
        "lead_steps_median": leads[len(leads) // 2] if leads else None,
        "per_episode": [
            [log.seed, bool(log.success), failing_throw_end(log), f and f["step"], f and f["cause"]]
            for log, f in zip(logs, flags, strict=True)
        ],
    }
