"""The running suture's high level: subtasks from the measured pose alone, switched on jaw events and the pull's
travel, and against the scripted expert's own stages on a whole suture."""

import numpy as np
import pytest

from lerobot_suture.subtasks import SubtaskRules, SubtaskRulesConfig


def pose(x: float, jaw: float) -> np.ndarray:
    """A measured pose at ``x`` (m) along world x with jaw closure ``jaw``."""
    return np.array([x, 0.0, 0.02, 1, 0, 0, 0, 1, 0, jaw])


def test_a_throw_runs_through_its_four_subtasks_and_the_next_throw_counts():
    rules = SubtaskRules(SubtaskRulesConfig(pulled_out_travel=0.01))
    assert rules.reset(pose(0.0, 0.88)) == ("insert", 0)  # the needle held: a suture starts at the insert
    steps = [
        (pose(0.001, 0.88), ("insert", 0)),
        (pose(0.001, 0.1), ("extract", 0)),  # lets go of the needle
        (pose(0.005, 0.0), ("extract", 0)),  # reaches the tip, open
        (pose(0.005, 0.8), ("extract", 0)),  # closes on it
        (pose(0.010, 0.88), ("extract", 0)),  # pulls 5 mm
        (pose(0.016, 0.88), ("lay_down", 0)),  # 11 mm: the needle is out
        (pose(0.020, 0.1), ("pick_up", 0)),  # lets go on the phantom
        (pose(0.020, 0.85), ("insert", 1)),  # grasps it again: the next throw
    ]
    for measured, expected in steps:
        assert rules.update(measured) == expected


def test_a_suture_from_a_needle_on_the_phantom_starts_with_its_pick_up():
    rules = SubtaskRules()
    assert rules.reset(pose(0.0, 0.0)) == ("pick_up", 0)
    assert rules.update(pose(0.0, 0.9)) == ("insert", 0)  # the first grasp leads into throw 0


def test_bad_settings_and_poses_are_refused():
    with pytest.raises(ValueError, match="closed_above"):
        SubtaskRulesConfig(closed_above=1.0)
    with pytest.raises(ValueError, match="pulled_out_travel"):
        SubtaskRulesConfig(pulled_out_travel=float("nan"))
    with pytest.raises(ValueError, match="measured pose"):
        SubtaskRules().reset(np.zeros(7))


def test_the_rules_follow_the_expert_s_stages_through_a_running_suture():
    """On a whole running suture of the scripted expert, the rules read the measured pose only and agree with the
    expert's stage on nearly every step, and count the same throws as the env."""
    from lerobot_suture.expert import ScriptedExpert
    from lerobot_suture.registration import make_suture_env

    env = make_suture_env(task="running_suture", obs_type="pixels_agent_pos", image_size=32)
    expert, rules = ScriptedExpert(), SubtaskRules()
    observation, info = env.reset(seed=0)
    expert.reset(env)
    ours, theirs = [rules.reset(observation["agent_pos"])], []
    while True:
        action = expert.act(env)
        theirs.append(expert._plan.stage)
        observation, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break
        ours.append(rules.update(observation["agent_pos"]))
    env.close()
    assert info["is_success"]
    agreement = np.mean([stage == subtask for stage, (subtask, _) in zip(theirs, ours, strict=True)])
    assert agreement > 0.97
    assert [throw for _, throw in ours][-1] == info["throw_index"] == 3
    assert {subtask for subtask, _ in ours} == {"insert", "extract", "lay_down", "pick_up"}


def test_a_gate_per_stage_is_fitted_on_successful_segments_and_flags_the_segment_it_falls_in(tmp_path):
    """FAIL-Detect's convention at toy scale: each subtask's threshold is the conformal quantile of its successful
    segments' maxima (a failed segment's scores are left out), a new segment starts a fresh maximum, and the
    first flag is latched with its segment."""
    from lerobot_suture.safety.ood.stage_gate import StageGate, StageThresholds, fit_stage_thresholds

    rng = np.random.default_rng(0)
    scores, stages, segments, successful = [], [], [], []
    for segment in range(120):
        stage, scale = ("insert", 1.0) if segment % 2 else ("extract", 10.0)
        ok = segment % 10 != 3  # every tenth segment failed: its scores are 100 times larger
        for _ in range(5):
            scores.append(scale * rng.uniform() * (1.0 if ok else 100.0))
            stages.append(stage)
            segments.append(segment)
            successful.append(ok)
    thresholds = fit_stage_thresholds(scores, stages, segments, successful, alpha=0.05)
    assert thresholds.segments == {"insert": 48, "extract": 60}  # the failed twelve are insert segments
    assert 0.9 < thresholds.thresholds["insert"] <= 1.0 and 9.0 < thresholds.thresholds["extract"] <= 10.0
    thresholds.save(tmp_path)
    assert StageThresholds.load(tmp_path) == thresholds

    gate = StageGate(thresholds)
    assert not gate.update("extract", 0, 5.0)  # in extract's spread
    assert not gate.update("insert", 0, 0.5)  # a new segment: extract's 5.0 does not carry over
    assert gate.update("insert", 0, 2.0) and gate.flagged_segment == ("insert", 0)
    assert gate.update("extract", 1, 0.0) and gate.flagged_segment == ("insert", 0)  # latched
    gate.reset()
    assert not gate.flagged and not gate.update("lay_down", 0, 1e9)  # a subtask without a threshold
    with pytest.raises(ValueError, match="at least 99 successful segments"):
        fit_stage_thresholds(scores, stages, segments, successful, alpha=0.01)
