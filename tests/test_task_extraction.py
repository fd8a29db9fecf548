"""The `extraction` task: the finished throw it starts from, the tissue holding a released needle, the
regrasp and the pull along the arc, what counts as done, and the expert in each scenario."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

from lerobot_suture.expert import ExpertConfig, ScriptedExpert, iter_expert_steps
from lerobot_suture.sim.extraction import PROTRUSION_RANGE, STRAIN_BOUND
from lerobot_suture.sim.geometry import jaw_holding, pose_vector
from lerobot_suture.sim.task import ENTRY_TOLERANCE, EXIT_TOLERANCE
from lerobot_suture.sim.tasks import TASKS

EXTRACTION_ID = TASKS["extraction"].gym_id


def make(**kwargs) -> gym.Env:
    kwargs.setdefault("obs_type", "state")
    return gym.make(EXTRACTION_ID, disable_env_checker=True, **kwargs)


def run_expert(env, seed):
    obs, _ = env.reset(seed=seed)
    return list(iter_expert_steps(env, ScriptedExpert(), obs))


def test_an_episode_starts_from_a_finished_throw_held_at_the_tail():
    env = make()
    for seed in range(4):
        _, info = env.reset(seed=seed)
        u = env.unwrapped
        assert u.needle_grasped and info["needle_in_tissue"]
        assert info["entry_error_m"] < ENTRY_TOLERANCE and info["exit_error_m"] < EXIT_TOLERANCE
        low, high = PROTRUSION_RANGE
        assert low * 0.01 - 1e-4 <= info["protrusion_m"] <= 2 * 0.01 * math.sin(high / 2) + 1e-4
        assert info["tissue_strain"] < 1e-9 and not info["is_success"]
        assert math.isinf(u.tail_exit_error)  # the tail has not left the tissue yet
        assert abs(u.grasp_parameters[0] - math.radians(165)) <= math.radians(4) + 1e-9


def test_a_released_needle_stays_lodged_and_moves_with_the_phantom():
    env = make()
    env.reset(seed=1)
    u = env.unwrapped
    jaw = u.jaw_pose()
    env.step(pose_vector(*jaw, 0.0))  # open: the tissue holds it
    assert not u.needle_grasped and u.needle_in_tissue
    centre, rotation = u.needle_pose()
    away = jaw[0] - 0.008 * jaw[1][:, 2]
    for _ in range(10):
        env.step(pose_vector(away, jaw[1], 0.0))
    np.testing.assert_allclose(u.needle_pose()[0], centre, atol=1e-9)  # no fall, no drift
    shift = np.array([0.003, -0.002, 0.0])
    u.set_phantom_pose(u.phantom_position + shift, u.phantom_yaw)
    env.step(pose_vector(away, jaw[1], 0.0))
    np.testing.assert_allclose(u.needle_pose()[0], centre + shift, atol=1e-9)
    np.testing.assert_allclose(u.needle_pose()[1], rotation, atol=1e-9)


def test_the_expert_extracts_the_needle_through_the_exit_hole():
    env = make()
    for seed in range(4):
        steps = run_expert(env, seed)
        last = steps[-1]
        assert last.terminated and last.info["is_success"], seed
        assert not last.info["needle_in_tissue"] and last.info["tissue_strain"] < STRAIN_BOUND / 4
        assert env.unwrapped.tail_exit_error < EXIT_TOLERANCE
        assert len(steps) < TASKS["extraction"].max_episode_steps


def closings(env, seed: int, config: ExpertConfig) -> tuple[list[str], list]:
    """The capture rule of each time the expert's jaw closed on the free needle, judged on the state its
    step started from (as the env judges it), and the episode's steps."""
    obs, _ = env.reset(seed=seed)
    u, expert = env.unwrapped, ScriptedExpert(config)
    expert.reset(env)
    rules, steps, before = [], [], u.capture_verdict()
    for step in iter_expert_steps(env, expert, obs):
        if step.action[9] >= 0.5 > (steps[-1].action[9] if steps else 1.0):
            rules.append(before.rule)
        steps.append(step)
        before = u.capture_verdict()
    return rules, steps


@pytest.mark.parametrize("seed", [0, 5])
def test_a_missed_first_regrasp_is_recovered_within_the_episode(seed):
    env = make()
    rules, steps = closings(env, seed, ExpertConfig())
    assert rules == ["caught"] and steps[-1].info["is_success"]
    rules, missed = closings(env, seed, ExpertConfig(regrasp_miss=0.001))
    assert rules[0] in ("lodged", "not_between_faces") and rules[1:] == ["caught"], rules
    last = missed[-1]
    assert last.terminated and last.info["is_success"] and last.info["tissue_strain"] < STRAIN_BOUND / 2
    assert len(steps) < len(missed) < TASKS["extraction"].max_episode_steps


class _Executed(gym.Wrapper):
    """Keeps every action the env executes."""

    def __init__(self, env):
        super().__init__(env)
        self.actions = []

    def step(self, action):
        self.actions.append(np.array(action))
        return self.env.step(action)


def test_regrasp_noise_is_executed_on_the_reach_and_never_recorded():
    env = _Executed(make())
    obs, _ = env.reset(seed=2)
    expert = ScriptedExpert(ExpertConfig(regrasp_noise=0.0004))
    labels, regrasping = [], []
    for step in iter_expert_steps(env, expert, obs):
        labels.append(step.action)
        regrasping.append(expert._plan.regrasping)
    assert step.terminated and step.info["is_success"]
    labels, executed, regrasping = np.array(labels), np.array(env.actions), np.array(regrasping)
    moved = np.linalg.norm(executed[:, :3] - labels[:, :3], axis=1)
    assert regrasping.sum() > 10 and np.all(moved[regrasping] > 0) and np.all(moved[~regrasping] == 0)
    assert 0.0002 < np.median(moved[regrasping]) < 0.0012  # 0.4 mm per axis
    np.testing.assert_array_equal(executed[:, 3:], labels[:, 3:])  # rotation and jaw as the expert's
    quiet = _Executed(make())
    obs, _ = quiet.reset(seed=2)
    plain = [s.action for s in iter_expert_steps(quiet, ScriptedExpert(ExpertConfig()), obs)]
    np.testing.assert_array_equal(np.array(quiet.actions), np.array(plain))  # off: the label is executed


def test_regrasp_miss_out_of_range_names_its_range():
    ExpertConfig(regrasp_miss=0.0006)
    for bad in (0.0003, 0.004, -0.001, math.nan):
        with pytest.raises(ValueError, match=r"`regrasp_miss` must be 0 .* \[0.0006, 0.003\]"):
            ExpertConfig(regrasp_miss=bad)


@pytest.mark.parametrize("scenario", [s for s in TASKS["extraction"].scenarios if s != "nominal"])
def test_every_scenario_of_extraction_happens_and_the_expert_still_extracts(scenario):
    env = make(scenario=scenario)
    steps = run_expert(env, seed=3)
    assert any(s.info["perturbed"] for s in steps)
    assert steps[-1].info["is_success"], scenario
    if scenario == "needle_drop":
        # Lost in the middle of the pull, lodged in the tissue, caught again and pulled out.
        assert env.unwrapped._grasp.captures == 2


def test_yanking_the_needle_out_strains_the_tissue_and_is_no_success():
    env = make()
    env.reset(seed=2)
    u = env.unwrapped
    position, rotation = u.jaw_pose()
    up = u.phantom_rotation[:, 2]
    terminated = False
    for k in range(40):  # straight up, off the arc, holding the tail
        _, _, terminated, _, info = env.step(pose_vector(position + 0.0005 * (k + 1) * up, rotation, 1.0))
        if terminated:
            break
    assert info["tissue_strain"] > STRAIN_BOUND and not info["is_success"]


def test_pulling_it_back_out_through_the_entry_is_no_success():
    env = make()
    env.reset(seed=0)
    u = env.unwrapped
    frame = u.insertion_frame()
    relative = frame.start_rotation.T @ u.needle_pose()[1]
    drive = -math.atan2(relative[1, 0], relative[0, 0])
    terminated = False
    while drive > -0.5 and not terminated:  # turn it back along its arc, the tail leading out of the entry
        drive -= 0.05
        target = jaw_holding(frame.centre, frame.needle_rotation(drive), *u.grasp_in_jaw)
        _, _, terminated, _, info = env.step(pose_vector(*target, 1.0))
    assert not info["needle_in_tissue"] and not info["is_success"]
