"""The running suture's high level: subtasks from the measured pose alone, switched on jaw events and the pull's
travel, and against the scripted expert's own stages on a whole suture."""

import numpy as np
import pytest
from policy_builders import ExpertAsPolicy

from lerobot_suture.sim.subtasks import SubtaskRules, SubtaskRulesConfig


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
        (pose(0.005, 0.8), ("extract", 0)),  # the jaw stops on the wire: the hold starts here
        (pose(0.010, 0.88), ("extract", 0)),  # pulls 5 mm
        (pose(0.016, 0.88), ("lay_down", 0)),  # 11 mm: the needle is out
        (pose(0.020, 0.1), ("pick_up", 1)),  # lets go on the phantom: the next throw's pick-up
        (pose(0.020, 0.85), ("pick_up", 1)),  # closes on it
        (pose(0.020, 0.85), ("insert", 1)),  # stopped on the wire: grasped again
    ]
    for measured, expected in steps:
        assert rules.update(measured) == expected


def test_with_the_wound_s_marks_a_needle_lost_on_the_way_is_picked_up_again_in_the_same_throw():
    rules = SubtaskRules()
    marks = np.array([0.0, 0.0, 0.02, 0.016, 0.0, 0.02])  # entry and exit at the poses' height, 16 mm apart
    rules.reset(pose(0.03, 0.88))
    assert rules.update(pose(0.03, 0.1), marks) == ("pick_up", 0)  # 30 mm from the entry: dropped
    assert rules.update(pose(0.03, 0.9), marks) == ("pick_up", 0)  # closing
    assert rules.update(pose(0.03, 0.9), marks) == ("insert", 0)  # stopped on the wire: the same throw
    assert rules.update(pose(0.005, 0.1), marks) == (
        "extract",
        0,
    )  # let go 5 mm from the entry: the insert is done


def test_a_jaw_closed_beside_the_needle_neither_pulls_it_out_nor_picks_it_up():
    """An empty jaw closes fully (1); the needle's wire stops it short. A closing beside the tip starts no pull,
    however far the jaw then travels, and a closing beside the needle on the phantom ends no pick-up."""
    rules = SubtaskRules(SubtaskRulesConfig(pulled_out_travel=0.01))
    rules.reset(pose(0.0, 0.88))
    assert rules.update(pose(0.0, 0.1)) == ("extract", 0)
    assert rules.update(pose(0.005, 1.0)) == ("extract", 0)  # closed on nothing
    assert rules.update(pose(0.030, 1.0)) == ("extract", 0)  # 25 mm of travel, no needle in the jaw
    assert rules.update(pose(0.030, 0.0)) == ("extract", 0)  # opens to try again
    assert rules.update(pose(0.030, 0.86)) == ("extract", 0)  # closing on the tip
    assert rules.update(pose(0.030, 0.86)) == ("extract", 0)  # stopped on the wire: the pull starts here
    assert rules.update(pose(0.041, 0.86)) == ("lay_down", 0)
    assert rules.update(pose(0.041, 0.0)) == ("pick_up", 1)
    assert rules.update(pose(0.041, 1.0)) == ("pick_up", 1)  # missed the needle on the phantom
    assert rules.update(pose(0.041, 0.0)) == ("pick_up", 1)
    assert rules.update(pose(0.041, 0.88)) == ("pick_up", 1)
    assert rules.update(pose(0.041, 0.88)) == ("insert", 1)
    assert SubtaskRules().reset(pose(0.0, 1.0)) == ("pick_up", 0)  # an empty jaw holds no needle to insert
    every_closing = SubtaskRules(SubtaskRulesConfig(holding_below=1.5))
    every_closing.reset(pose(0.0, 1.0))
    assert every_closing.subtask == "insert"


def test_a_jaw_closing_on_nothing_is_no_grasp_on_its_way_through_the_wire_s_readings():
    """An empty jaw closes fully over a few control steps and reads 0.5-0.95 on the way, as a jaw on the wire does;
    the rules judge a closing once the jaw has stopped, so it neither ends a pick-up nor starts a pull."""
    rules = SubtaskRules(SubtaskRulesConfig(pulled_out_travel=0.01))
    rules.reset(pose(0.0, 0.0))
    for jaw in (0.3, 0.51, 0.82, 1.0, 1.0):
        assert rules.update(pose(0.0, jaw)) == ("pick_up", 0)
    assert rules.update(pose(0.0, 0.0)) == ("pick_up", 0)
    for jaw, expected in ((0.6, "pick_up"), (0.86, "pick_up"), (0.86, "insert")):
        assert rules.update(pose(0.0, jaw)) == (expected, 0)
    assert rules.update(pose(0.0, 0.0)) == ("extract", 0)
    for jaw in (0.51, 0.9, 1.0):  # a regrasp's closing beside the tip, then 15 mm of travel
        assert rules.update(pose(0.0, jaw)) == ("extract", 0)
    assert rules.update(pose(0.015, 1.0)) == ("extract", 0)


def test_a_reading_is_the_vector_it_was_made_into():
    from lerobot_suture.sim.subtasks import SUBTASKS, subtask_reading, subtask_vector

    for subtask in SUBTASKS:
        for throw in range(4):
            assert subtask_reading(subtask_vector(subtask, throw)) == (subtask, throw)
    for bad in (np.zeros(5), np.array([1, 1, 0, 0, 0.0]), np.array([1, 0, 0, 0, 0.5]), np.ones(4)):
        with pytest.raises(ValueError, match="one-hot"):
            subtask_reading(bad)


def test_a_suture_from_a_needle_on_the_phantom_starts_with_its_pick_up():
    rules = SubtaskRules()
    assert rules.reset(pose(0.0, 0.0)) == ("pick_up", 0)
    assert rules.update(pose(0.0, 0.9)) == ("pick_up", 0)  # closing
    assert rules.update(pose(0.0, 0.9)) == ("insert", 0)  # the first grasp leads into throw 0


def test_bad_settings_and_poses_are_refused():
    with pytest.raises(ValueError, match="closed_above"):
        SubtaskRulesConfig(closed_above=1.0)
    with pytest.raises(ValueError, match="pulled_out_travel"):
        SubtaskRulesConfig(pulled_out_travel=float("nan"))
    with pytest.raises(ValueError, match="holding_below"):
        SubtaskRulesConfig(holding_below=0.4)
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
        theirs.append(expert.stage)
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
    gate.enter("extract", 0)
    assert not gate.update(5.0)  # in extract's spread
    gate.enter("insert", 0)
    assert not gate.update(0.5)  # a new segment: extract's 5.0 does not carry over
    assert gate.update(2.0) and gate.update(0.1) and gate.flags == [("insert", 0)]  # latched in its segment
    gate.enter("extract", 1)
    assert not gate.update(0.0) and gate.flags == [("insert", 0)]  # the next segment starts afresh
    gate.reset()
    gate.enter("lay_down", 0)
    assert not gate.flags and not gate.update(1e9)  # a subtask without a threshold
    with pytest.raises(ValueError, match="at least 99 successful segments"):
        fit_stage_thresholds(scores, stages, segments, successful, alpha=0.01)


class _StepScores:
    """A score every 4 control steps: 10 inside ``[high_from, high_to)``, 0.1 elsewhere."""

    kind = "test"

    def __init__(self, high_from: int, high_to: int):
        self.high = range(high_from, high_to)

    def reset(self, rows):
        self.step = -1

    def observe(self, row, observation):
        self.step += 1

    def status(self, row):
        score = 10.0 if self.step in self.high else 0.1
        new = self.step % 4 == 0
        return {"score": score, "threshold": 1.0, "decision": False, "released": False, "new_prediction": new}

    def rearm(self, row):
        pass

    def context(self, row):
        return {}

    def close(self):
        pass


def test_a_flagged_subtask_is_taken_over_by_the_expert_and_handed_back_for_the_next():
    """The stage gate enforced on a whole running suture: scores jump during the second throw's extraction; the
    gate flags that segment, the scripted surgeon takes that extraction over and hands back once it is done, and
    the suture completes with the policy driving the rest."""
    from lerobot_suture.registration import make_suture_env
    from lerobot_suture.runtime.gates import StageGates
    from lerobot_suture.runtime.rollout import rollout_episode
    from lerobot_suture.safety.ood.stage_gate import StageThresholds

    env = make_suture_env(task="running_suture", obs_type="pixels_agent_pos", image_size=32)
    subtasks = ("insert", "extract", "lay_down", "pick_up")
    thresholds = StageThresholds(dict.fromkeys(subtasks, 1.0), dict.fromkeys(subtasks, 100), alpha=0.01)
    gates = StageGates(_StepScores(340, 344), thresholds)  # throw 2's extraction runs from about step 325
    log = rollout_episode(env, ExpertAsPolicy(env), 0, "expert_per_subtask", gates=gates)
    env.close()
    assert log.success and log.handover_cause == "gate"
    (taken, _, _, why), (back, _, _, why_back) = log.handovers
    assert (why, why_back) == ("gate released", "handed back")
    assert {s.subtask for s in log.steps[taken - 1 : taken + 1]} == {"extract"}
    assert all(s.controller == "surgeon" and not s.consulted for s in log.steps[taken + 1 : back])
    # It hands back as the extraction ends: the high level reads the pull's end a few steps before the expert.
    laid = next(k for k in range(taken, back + 1) if log.steps[k].subtask == "lay_down")
    assert 0 <= back - laid <= 5
    assert log.steps[back].subtask == "lay_down" and log.steps[back].controller == "policy"
    assert [s.subtask for s in log.steps if s.consulted][-1] == "insert"  # the policy drove to the last throw


def test_stage_thresholds_come_from_the_segments_of_successful_sutures(tiny_policy_dir, tmp_path, capsys):
    """The loop's logs name each step's subtask, and ``stage_thresholds`` cuts them into segments; an insertion
    policy that never finishes a suture has no successful segment, and ``calibrate --per_stage`` says so."""
    from lerobot_suture.cli import main as cli_main
    from lerobot_suture.registration import make_suture_env
    from lerobot_suture.runtime.calibration import stage_thresholds
    from lerobot_suture.runtime.gates import StageGates
    from lerobot_suture.runtime.rollout import rollout_episode

    env = make_suture_env(task="running_suture", obs_type="pixels_agent_pos", image_size=32)
    logs = [
        rollout_episode(env, ExpertAsPolicy(env), seed, gates=StageGates(_StepScores(0, 0), None))
        for seed in (0, 1)
    ]
    env.close()
    assert all(log.success for log in logs)
    stages = stage_thresholds(logs, alpha=0.3)
    assert stages.segments == {"insert": 8, "extract": 6, "lay_down": 6, "pick_up": 6}
    assert stages.thresholds == dict.fromkeys(stages.thresholds, 0.1)
    import shutil

    policy = shutil.copytree(tiny_policy_dir, tmp_path / "policy")
    args = ["calibrate", f"--policy.path={policy}", "--per_stage=true", "--calibration_episodes=2"]
    with pytest.raises(SystemExit) as exit_info:
        cli_main([*args, "--mode=per_prediction", "--holdout_episodes=0"])
    assert exit_info.value.code == 2
    assert "successful segments per subtask" in capsys.readouterr().err
    assert sorted(p.name for p in policy.iterdir()) == sorted(p.name for p in tiny_policy_dir.iterdir())


def test_the_subtask_as_an_observation_follows_the_rules_after_the_marks_and_leaves_the_episode_as_it_was():
    """``subtask=True`` appends the high level's one-hot subtask and throw to ``environment_state``, after the
    wound's marks; the physics and ``agent_pos`` are those of the same episode without it."""
    import gymnasium as gym

    from lerobot_suture.expert import ScriptedExpert
    from lerobot_suture.sim.subtasks import SUBTASK_NAMES, SubtaskObservation, subtask_vector

    kwargs = dict(obs_type="pixels_agent_pos", image_size=32, disable_env_checker=True, marks=True)
    plain = gym.make("lerobot_suture/RunningSuture-v0", **kwargs)
    with_subtask = gym.make("lerobot_suture/RunningSuture-v0", subtask=True, **kwargs)
    assert with_subtask.observation_space["environment_state"].shape == (6 + len(SUBTASK_NAMES),)
    expert, rules = ScriptedExpert(), SubtaskRules()
    a, _ = plain.reset(seed=4)
    b, _ = with_subtask.reset(seed=4)
    expert.reset(plain)
    reading = rules.reset(a["agent_pos"])
    seen = set()
    for _ in range(130):  # the first throw's insert and the start of its extraction
        np.testing.assert_array_equal(a["agent_pos"], b["agent_pos"])
        np.testing.assert_array_equal(b["environment_state"][:6], a["environment_state"])
        np.testing.assert_array_equal(b["environment_state"][6:], subtask_vector(*reading))
        seen.add(reading)
        action = expert.act(plain)
        a, *_ = plain.step(action)
        b, *_ = with_subtask.step(action)
        reading = rules.update(a["agent_pos"], a["environment_state"])
    assert seen == {("insert", 0), ("extract", 0)}
    plain.close()
    with_subtask.close()
    with pytest.raises(ValueError, match="privileged"):
        SubtaskObservation(gym.make("lerobot_suture/NeedleInsertion-v0", obs_type="state"))


def test_a_recording_with_the_subtask_stores_it_and_a_policy_that_reads_it_gets_it(tmp_path):
    from types import SimpleNamespace

    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_suture.datasets.card import render_description
    from lerobot_suture.datasets.features import ENV_STATE_KEY
    from lerobot_suture.datasets.record import record
    from lerobot_suture.datasets.record_config import RecordConfig
    from lerobot_suture.runtime.policy import env_kwargs_for_policy
    from lerobot_suture.sim.subtasks import SUBTASK_NAMES
    from lerobot_suture.sim.wound_marks import MARKS_NAMES

    root = tmp_path / "data"
    cfg = dict(
        repo_id="suture-tests/subtask", root=str(root), image_size=32, num_episodes=1, val_fraction=0.0
    )
    record(RecordConfig(**cfg, marks=True, subtask=True))
    dataset = LeRobotDataset("suture-tests/subtask", root=root)
    assert dataset.meta.features[ENV_STATE_KEY]["names"] == [*MARKS_NAMES, *SUBTASK_NAMES]
    np.testing.assert_array_equal(dataset[0][ENV_STATE_KEY].numpy()[6:], [1, 0, 0, 0, 0])  # insert, throw 0
    assert "--subtask=true" in RecordConfig(**cfg, subtask=True).command()
    card = render_description(root)
    assert "subtask (`observation.environment_state`, after the marks)" in card
    with pytest.raises(ValueError, match="--subtask=false|subtask"):
        record(RecordConfig(**{**cfg, "num_episodes": 2}, marks=True, resume=True))
    with pytest.raises(ValueError, match="--obs_type=pixels_agent_pos"):
        RecordConfig(**cfg, obs_type="state", subtask=True)

    image = PolicyFeature(type=FeatureType.VISUAL, shape=(3, 32, 32))
    features = {
        "observation.images.endoscope": image,
        "observation.state": PolicyFeature(FeatureType.STATE, (10,)),
    }
    for size, extra in ((5, {"subtask": True}), (11, {"marks": True, "subtask": True}), (6, {"marks": True})):
        state = {ENV_STATE_KEY: PolicyFeature(type=FeatureType.ENV, shape=(size,))}
        kwargs = env_kwargs_for_policy(SimpleNamespace(input_features={**features, **state}))
        assert kwargs == {"obs_type": "pixels_agent_pos", "image_size": 32, **extra}


def test_a_stage_that_outlasts_its_time_budget_is_flagged_and_the_next_starts_afresh(tmp_path):
    """The budget is the conformal quantile of successful segments' durations; a segment flags on the step that
    takes it past its subtask's budget, through the stage gates of a rollout, and a subtask without one never."""
    from lerobot_suture.runtime.gates import SilentGates, StageGates
    from lerobot_suture.safety.ood.stage_gate import StageBudgets, fit_stage_budgets

    budgets = fit_stage_budgets(
        {"insert": list(range(60, 160)), "extract": [3] * 100}, alpha=0.01, source="test"
    )
    assert budgets.budgets == {"insert": 159, "extract": 3} and budgets.segments == {
        "insert": 100,
        "extract": 100,
    }
    budgets.save(tmp_path)
    assert StageBudgets.load(tmp_path) == budgets
    with pytest.raises(ValueError, match="at least 99 successful segments"):
        fit_stage_budgets({"insert": [70] * 98})
    with pytest.raises(ValueError, match="whole number"):
        StageBudgets({"insert": 0}, {"insert": 100}, 0.01)

    gates = StageGates(SilentGates(), None, budgets=budgets)
    gates.reset(1)
    released = []
    jaws = [
        0.88,
        0.1,
        0.1,
        0.1,
        0.1,
        0.1,
        0.86,
    ]  # insert, then an extract that waits four steps with the jaw open
    for jaw in jaws:
        gates.observe(0, {"agent_pos": pose(0.0, jaw)})
        released.append(gates.status(0)["released"])
    assert released == [
        False,
        False,
        False,
        False,
        True,
        True,
        True,
    ]  # the extract's fourth step is one too many
    assert gates.context(0) == {"subtask": "extract", "throw": 0}
    gates.observe(0, {"agent_pos": pose(0.0, 0.86)})  # the jaw stops on the wire: the hold starts
    gates.observe(0, {"agent_pos": pose(0.03, 0.86)})  # pulled out: lay down, which has no budget
    assert not gates.status(0)["released"]
