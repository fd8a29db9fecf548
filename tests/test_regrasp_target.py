"""The regrasp planned through the registered marks: the expert aimed at it, and the observation that gives it."""

from __future__ import annotations

import itertools

import gymnasium as gym
import numpy as np
import pytest

from lerobot_suture.expert import ExpertConfig, ScriptedExpert, iter_expert_steps
from lerobot_suture.runtime.policy import env_kwargs_for_policy
from lerobot_suture.sim.extraction import REGRASP_ANGLE, planned_regrasp
from lerobot_suture.sim.geometry import grasp_transform, jaw_holding, matrix_from_rot6
from lerobot_suture.sim.regrasp_target import REGRASP_TARGET_DIM, regrasp_target
from lerobot_suture.sim.tasks import TASKS

EXTRACTION_ID = TASKS["extraction"].gym_id


def make(**kwargs) -> gym.Env:
    kwargs.setdefault("obs_type", "pixels_agent_pos")
    kwargs.setdefault("image_size", 32)
    return gym.make(EXTRACTION_ID, disable_env_checker=True, **kwargs)


def test_the_planned_regrasp_lies_on_the_lodged_needle_whatever_its_protrusion():
    env = make(obs_type="state")
    for seed in range(6):
        env.reset(seed=seed)
        u = env.unwrapped
        planned = planned_regrasp(u.entry_point, u.exit_point, u.phantom_rotation[:, 2])
        # The needle's own grasp near its tip: the plan differs from it along the wire only.
        true_pos, true_rot = jaw_holding(*u.needle_pose(), *grasp_transform(REGRASP_ANGLE, 0.0, 0.0))
        centre, rotation = u.needle_pose()
        radius = np.linalg.norm(planned[0] - centre)
        assert abs(radius - np.linalg.norm(true_pos - centre)) < 1e-6  # on the needle's circle
        assert abs(rotation[:, 2] @ (planned[0] - centre)) < 1e-6  # in its plane
        # the jaw's axis on its normal
        np.testing.assert_allclose(planned[1][:, 2], true_rot[:, 2], atol=1e-6)
        assert np.linalg.norm(planned[0] - true_pos) < 0.0011  # half the protrusion range along the wire


@pytest.mark.parametrize(
    "scenario", ["nominal", *[s for s in TASKS["extraction"].scenarios if s != "nominal"]]
)
def test_the_expert_aimed_at_the_plan_catches_the_needle_at_its_first_closing(scenario):
    env = make(obs_type="state", scenario=scenario)
    for seed in (0, 1):
        obs, _ = env.reset(seed=seed)
        expert = ScriptedExpert(ExpertConfig(regrasp_aim="marks"))
        expert.reset(env)
        steps = list(iter_expert_steps(env, expert, obs))
        jaw = [s.action[9] for s in steps]
        closings = sum(now >= 0.5 > before for before, now in itertools.pairwise(jaw))
        assert steps[-1].info["is_success"], (scenario, seed)
        if scenario != "needle_drop":  # a dropped needle is caught a second time
            assert closings == 1, (scenario, seed)


def test_the_observation_is_the_motion_to_the_plan_in_the_jaw_frame():
    env = make(marks=True, regrasp_target=True)
    obs, _ = env.reset(seed=2)
    u = env.unwrapped
    assert obs["environment_state"].shape == (6 + REGRASP_TARGET_DIM,)
    np.testing.assert_allclose(obs["environment_state"][:3], u.entry_point, atol=1e-6)
    target = obs["environment_state"][6:]
    jaw_pos, jaw_rot = u.jaw_pose()
    planned_pos, planned_rot = planned_regrasp(u.entry_point, u.exit_point, u.phantom_rotation[:, 2])
    np.testing.assert_allclose(jaw_pos + jaw_rot @ target[:3], planned_pos, atol=1e-6)
    np.testing.assert_allclose(jaw_rot @ matrix_from_rot6(target[3:]), planned_rot, atol=1e-5)
    # Where the expert aimed at the plan closes the jaw, the observation reads the plan reached.
    expert = ScriptedExpert(ExpertConfig(regrasp_aim="marks"))
    expert.reset(env)
    for step in iter_expert_steps(env, expert, obs):
        if step.action[9] >= 0.5 and np.linalg.norm(step.obs["environment_state"][6:9]) < 1e-3:
            break
    else:
        pytest.fail("the expert never closed the jaw at the plan")
    # The physics, the images and the pose are those of the env without it.
    plain = make()
    plain_obs, _ = plain.reset(seed=2)
    again, _ = env.reset(seed=2)
    np.testing.assert_array_equal(plain_obs["pixels"]["endoscope"], again["pixels"]["endoscope"])
    np.testing.assert_array_equal(plain_obs["agent_pos"], again["agent_pos"])


@pytest.mark.parametrize("tip_trace", [False, True])
def test_the_target_is_seen_from_the_observation_s_own_pose_at_every_step(tip_trace):
    # With the tip trace off, rendering leaves the simulator's kinematics a physics step past agent_pos; the
    # target must not read them, or a policy trained on one setting sees an offset under the other.
    env = make(regrasp_target=True, record_tip_trace=tip_trace)
    obs, _ = env.reset(seed=4)
    u = env.unwrapped
    expert = ScriptedExpert(ExpertConfig(regrasp_aim="marks"))
    expert.reset(env)
    for step in list(iter_expert_steps(env, expert, obs))[:30]:
        pose = step.obs["agent_pos"].astype(np.float64)
        expected = regrasp_target(
            pose[:3], matrix_from_rot6(pose[3:9]), u.entry_point, u.exit_point, u.phantom_rotation[:, 2]
        )
        np.testing.assert_array_equal(step.obs["environment_state"], expected)


def test_the_plan_is_a_pure_function_of_the_registration_and_the_jaw():
    rng = np.random.default_rng(0)
    entry, exit_ = rng.normal(size=3) * 0.01, rng.normal(size=3) * 0.01
    exit_ = entry + np.array([0.006, 0.0, 0.0])
    normal = np.array([0.0, 0.0, 1.0])
    first = regrasp_target(np.zeros(3), np.eye(3), entry, exit_, normal)
    np.testing.assert_array_equal(first, regrasp_target(np.zeros(3), np.eye(3), entry, exit_, normal))
    moved = regrasp_target(np.array([0.001, 0.0, 0.0]), np.eye(3), entry, exit_, normal)
    np.testing.assert_allclose(moved[:3], first[:3] - [0.001, 0.0, 0.0], atol=1e-7)
    assert first.dtype == np.float32 and first.shape == (REGRASP_TARGET_DIM,)


def test_the_privileged_state_refuses_the_target_with_the_fix():
    with pytest.raises(ValueError, match="Pass obs_type='pixels_agent_pos'"):
        make(obs_type="pixels_agent_pos_state", regrasp_target=True)


@pytest.mark.parametrize(
    "size, flags",
    [
        (9, {"regrasp_target"}),
        (15, {"marks", "regrasp_target"}),
        (14, {"subtask", "regrasp_target"}),
        (20, {"marks", "subtask", "regrasp_target"}),
        (11, {"marks", "subtask"}),
        (18, set()),
    ],
)
def test_a_policy_s_environment_state_names_the_env_it_runs_in(size, flags):
    from lerobot.configs import FeatureType, PolicyFeature

    class Config:
        input_features = {
            "observation.images.endoscope": PolicyFeature(type=FeatureType.VISUAL, shape=(3, 32, 32)),
            "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(10,)),
            "observation.environment_state": PolicyFeature(type=FeatureType.ENV, shape=(size,)),
        }

    kwargs = env_kwargs_for_policy(Config())
    assert {k for k in ("marks", "subtask", "regrasp_target") if kwargs.get(k)} == flags
    assert kwargs["obs_type"] == ("pixels_agent_pos_state" if size == 18 else "pixels_agent_pos")
    env = make(**kwargs)
    obs, _ = env.reset(seed=0)
    assert obs["environment_state"].shape == (size,)


def test_a_settled_regrasp_holds_the_open_jaw_still_on_the_plan_before_it_closes():
    env = make(obs_type="state")
    for seed in (0, 1):
        obs, _ = env.reset(seed=seed)
        expert = ScriptedExpert(ExpertConfig(regrasp_aim="marks", regrasp_settle=3))
        expert.reset(env)
        steps = list(iter_expert_steps(env, expert, obs))
        assert steps[-1].info["is_success"], seed
        jaw = [s.action[9] for s in steps]
        close = next(i for i in range(1, len(jaw)) if jaw[i] >= 0.5 > jaw[i - 1])
        assert sum(now >= 0.5 > before for before, now in itertools.pairwise(jaw)) == 1, seed
        # The closing and the three steps before it command the same pose, with the jaw open before it.
        held = np.stack([s.action[:9] for s in steps[close - 3 : close + 1]])
        np.testing.assert_allclose(held, held[0][None].repeat(4, axis=0), atol=1e-6)
        assert all(jaw[i] < 0.5 for i in range(close - 3, close))


def test_the_settle_is_a_whole_number_of_steps_within_its_range():
    for bad in (-1, 11, 1.5):
        with pytest.raises(ValueError, match="regrasp_settle"):
            ExpertConfig(regrasp_settle=bad)


def test_a_reach_that_ends_beside_the_grasp_is_corrected_by_the_advance():
    env = make(obs_type="state")
    for seed in (0, 1, 2):
        obs, _ = env.reset(seed=seed)
        expert = ScriptedExpert(
            ExpertConfig(regrasp_aim="marks", regrasp_settle=3, regrasp_reach_offset=0.001)
        )
        expert.reset(env)
        u = env.unwrapped
        lateral, phases = [], []
        for step in iter_expert_steps(env, expert, obs):
            jaw_pos, _ = u.jaw_pose()
            grasp_pos, grasp_rot = planned_regrasp(u.entry_point, u.exit_point, u.phantom_rotation[:, 2])
            lateral.append(float(np.linalg.norm(grasp_rot[:, :2].T @ (jaw_pos - grasp_pos))))
            phases.append(expert._plan.phase)
            success = step.info["is_success"]
        assert success, seed
        advance = phases.index("advance")
        assert 0.0001 < lateral[advance - 1] < 0.0011, seed  # the reach ended beside the line
        assert lateral[phases.index("close") - 1] < 0.0002, seed  # the closing is on it
