"""What a gate per stage would have flagged on running sutures: segments, budgets and first flags replayed from
episode logs, the catches counted before the failing throw ends."""

from __future__ import annotations

import math

import pytest

from lerobot_suture.experiments.stage_alarms import (
    failing_throw_end,
    first_flag,
    stage_alarm_table,
    stage_durations,
)
from lerobot_suture.runtime.calibration import stage_thresholds
from lerobot_suture.runtime.rollout import EpisodeLog, StepLog
from lerobot_suture.safety.ood.stage_gate import StageBudgets, StageThresholds, segment_runs

THROW = ["insert"] * 8 + ["extract"] * 4 + ["lay_down"] * 3 + ["pick_up"] * 3


def _log(subtasks, scores=None, success=True, results=(), seed=0) -> EpisodeLog:
    """An episode whose steps name ``subtasks``; ``scores``: step -> a new prediction's score."""
    scores = scores or {}
    steps = [
        StepLog(
            score=scores.get(k, math.nan),
            threshold=math.nan,
            ood=False,
            released=False,
            new_prediction=k in scores,
            controller="policy",
            perturbed=False,
            needle_in_tissue=False,
            subtask=subtask,
        )
        for k, subtask in enumerate(subtasks)
    ]
    return EpisodeLog(
        seed=seed, scenario="nominal", success=success, steps=steps, throw_results=list(results)
    )


def test_segments_are_runs_of_one_subtask_and_the_throw_counts_inserts():
    runs = segment_runs(THROW + ["insert"] * 2)
    assert runs == [
        ("insert", 0, 0, 8),
        ("extract", 0, 8, 12),
        ("lay_down", 0, 12, 15),
        ("pick_up", 0, 15, 18),
        ("insert", 1, 18, 20),
    ]
    assert segment_runs(["pick_up", "insert"]) == [("pick_up", 0, 0, 1), ("insert", 0, 1, 2)]
    assert segment_runs([]) == []


def test_durations_come_from_closed_sutures_and_leave_out_the_segment_the_episode_cut():
    closed = _log(THROW + ["insert"] * 5)
    failed = _log(THROW * 2, success=False)
    assert stage_durations([closed, failed]) == {
        "insert": [8],
        "extract": [4],
        "lay_down": [3],
        "pick_up": [3],
    }


def test_the_scored_subtasks_alone_get_thresholds():
    """A chain's scripted pick-up scores only where it falls back to a policy: ``subtasks`` leaves it out."""
    logs = [_log(THROW + ["insert"] * 2, {0: 1.0, 4: 2.0 + k, 16: 50.0}, seed=k) for k in range(3)]
    fitted = stage_thresholds(logs, alpha=0.3, subtasks=("insert",))
    assert fitted.segments == {"insert": 3} and fitted.thresholds["insert"] == pytest.approx(4.0)
    with pytest.raises(ValueError, match="pick_up"):
        stage_thresholds(logs[:1], alpha=0.3)  # pick_up has one segment, under what alpha 0.3 needs


THRESHOLDS = StageThresholds({"insert": 5.0}, {"insert": 100}, alpha=0.01)
BUDGETS = StageBudgets({"insert": 10, "extract": 6, "lay_down": 5, "pick_up": 5}, {}, alpha=0.01)


def test_the_first_flag_is_replayed_step_by_step_with_its_cause():
    assert first_flag(_log(THROW, {0: 1.0, 4: 4.9}), THRESHOLDS, BUDGETS) is None
    assert first_flag(_log(THROW, {0: 1.0, 4: 6.0}), THRESHOLDS, BUDGETS) == {
        "step": 4,
        "subtask": "insert",
        "throw": 1,
        "cause": "score",
    }
    stalled = _log(THROW[:12] + ["extract"] * 10)  # the extract runs 14 steps against a budget of 6
    assert first_flag(stalled, THRESHOLDS, BUDGETS) == {
        "step": 14,
        "subtask": "extract",
        "throw": 1,
        "cause": "budget",
    }
    assert first_flag(stalled, THRESHOLDS, None) is None
    second = _log(THROW + ["insert"] * 3, {19: 9.0})  # the second throw's insert
    assert first_flag(second, THRESHOLDS, None)["throw"] == 2


def test_a_failing_suture_is_caught_only_before_its_failing_throw_ends():
    off = {"on_marks": False, "over_step": 21}  # the env counts from 1: step 20 drove it through
    early = _log(THROW + ["insert"] * 3, {19: 9.0}, success=False, results=[{"on_marks": True}, off], seed=1)
    late = _log(THROW + ["insert"] * 3, {20: 9.0}, success=False, results=[{"on_marks": True}, off], seed=2)
    stalled = _log(THROW[:12] + ["extract"] * 10, success=False, results=[{"on_marks": True}], seed=3)
    quiet = _log(THROW + ["insert"] * 3, success=False, results=[{"on_marks": True}, off], seed=4)
    closed = _log(THROW + ["insert"] * 3, {19: 9.0}, seed=5)
    assert failing_throw_end(early) == 20 and failing_throw_end(stalled) == 21
    table = stage_alarm_table([early, late, stalled, quiet, closed, _log(THROW, seed=6)], THRESHOLDS, BUDGETS)
    assert table["failing_caught"]["count"] == 2 and table["failing_caught"]["of"] == 4
    assert table["successful_flagged"]["count"] == 1 and table["successful_flagged"]["of"] == 2
    assert table["caught_by"] == {"score": 1, "budget": 1}
    assert table["caught_in"] == {"insert 2": 1, "extract 1": 1}
    assert table["false_alarms_in"] == {"insert 2 (score)": 1}
    assert (
        table["lead_steps_median"] == 7
    )  # 1 step before the off-marks throw, 7 before the stalled one's end
    low, high = table["failing_caught"]["wilson_95"]
    assert low < 0.5 < high


def test_a_hand_back_inside_a_flagged_segment_gives_it_a_fresh_gate_and_budget():
    """The surgeon's part of a flagged extract is done while the high level still reads extract: the policy gets
    the segment's budget again instead of being flagged back at once, and each flag stays on record."""
    from lerobot_suture.safety.ood.stage_gate import StageGate

    gate = StageGate(THRESHOLDS, BUDGETS)
    gate.enter("extract", 0)
    assert not any(gate.tick() for _ in range(6)) and gate.tick()  # the 7th step outlasts the budget of 6
    assert gate.tick() and gate.flags == [("extract", 0)]  # latched, recorded once
    gate.rearm()  # handed back inside the segment
    assert not gate.flagged_here and not any(gate.tick() for _ in range(6)) and gate.tick()
    assert gate.flags == [("extract", 0), ("extract", 0)]
    gate.enter("extract", 0)  # the same segment read again: nothing changes
    assert gate.flagged_here
    gate.enter("insert", 1)
    assert not gate.flagged_here and not gate.update(4.0) and gate.update(6.0)
    assert gate.flags[-1] == ("insert", 1)
