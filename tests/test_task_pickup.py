"""The `pickup` task: the needle on the phantom, the jaw that catches it, the expert, the scenarios, LeRobot's
env type, and `insertion` left exactly as it was."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

from lerobot_suture.expert import ScriptedExpert, iter_expert_steps
from lerobot_suture.registration import ENV_ID
from lerobot_suture.sim.geometry import (
    grasp_transform,
    jaw_holding,
    matrix_from_rotvec,
    needle_arc_points,
    pose_vector,
)
from lerobot_suture.sim.pickup import LIFT_HEIGHT, REST_RANGE_XY, grasp_ready_for_throw
from lerobot_suture.sim.suture_env import SutureEnv
from lerobot_suture.sim.task import GRASP_ANGLE
from lerobot_suture.sim.tasks import TASKS

PICKUP_ID = TASKS["pickup"].gym_id


def make(**kwargs) -> gym.Env:
    kwargs.setdefault("obs_type", "state")
    return gym.make(PICKUP_ID, disable_env_checker=True, **kwargs)


def run_expert(env, seed):
    obs, _ = env.reset(seed=seed)
    steps = list(iter_expert_steps(env, ScriptedExpert(), obs))
    return steps


def test_registered_per_task_and_named_by_task_too():
    assert gym.spec(PICKUP_ID).max_episode_steps == TASKS["pickup"].max_episode_steps
    env = gym.make(PICKUP_ID, task="pickup", obs_type="state", disable_env_checker=True)
    assert (
        env.unwrapped.task_name == "pickup" and env.unwrapped.task_description == TASKS["pickup"].instruction
    )
    # The insertion id would cut a pickup at its 100 steps (of 120): refused, naming the pickup's id.
    with pytest.raises(ValueError, match=f"gym.make\\('{PICKUP_ID}'\\)"):
        gym.make(ENV_ID, task="pickup", obs_type="state", disable_env_checker=True)
    with pytest.raises(ValueError, match="`task` must be one of"):
        SutureEnv(task="knot_tying")
    with pytest.raises(ValueError, match="does not apply to task 'pickup'"):
        SutureEnv(task="pickup", scenario="phantom_moved_after_insertion")


def test_the_needle_rests_on_the_phantom_and_the_jaw_starts_open():
    env = make()
    for seed in range(5):
        obs, info = env.reset(seed=seed)
        u = env.unwrapped
        assert not u.needle_grasped and not info["needle_grasped"]
        assert obs["agent_pos"][9] == pytest.approx(0.0, abs=1e-6)  # jaw fully open
        centre, rotation = u.needle_pose()
        local = u.phantom_rotation.T @ (centre - u.phantom_position)
        assert np.all(np.abs(local[:2] - np.array([0.0, -0.004])) <= REST_RANGE_XY + 1e-9)
        assert rotation[:, 2] @ u.phantom_rotation[:, 2] == pytest.approx(
            -1.0
        )  # flat, normal into the tissue
        hold = pose_vector(*u.jaw_pose(), 0.0)
        for _ in range(10):
            env.step(hold)
        moved, _ = u.needle_pose()
        assert np.linalg.norm(moved - centre) < 1e-4  # it stays where it lies
        assert 0.0 < u.needle_clearance < 0.001


def _jaw_at_grasp(env, lift=0.0):
    """Put the open jaw at the nominal grasp pose of the resting needle (kinematic IK, then a step)."""
    u = env.unwrapped
    pos, rot = jaw_holding(*u.needle_pose(), *grasp_transform(GRASP_ANGLE, 0.0, 0.0))
    return pos + lift * u.phantom_rotation[:, 2], rot


def test_closing_the_jaw_on_the_needle_catches_it_and_lifting_it_succeeds():
    env = make()
    env.reset(seed=3)
    steps = run_expert(env, seed=3)
    last = steps[-1]
    assert last.terminated and last.info["is_success"]
    u = env.unwrapped
    assert u.needle_grasped and grasp_ready_for_throw(u.grasp_parameters, u.grasp_reversed)
    assert u.needle_clearance >= LIFT_HEIGHT
    angle, depth, roll = last.info["grasp_parameters"]
    assert abs(angle - GRASP_ANGLE) < math.radians(1) and abs(depth) < 2e-4 and abs(roll) < 0.02
    # The jaw reading shows the needle in the jaw, as in insertion.
    assert 0.8 < u.observe()["agent_pos"][9] < 0.95


def test_a_jaw_closed_away_from_the_needle_catches_nothing_and_a_closed_jaw_cannot_catch():
    env = make()
    env.reset(seed=0)
    u = env.unwrapped
    pos, rot = _jaw_at_grasp(env, lift=0.004)  # 4 mm above the wire: beyond the jaw tip
    for _ in range(25):
        env.step(pose_vector(pos, rot, 0.0))
    env.step(pose_vector(pos, rot, 1.0))
    assert not u.needle_grasped
    # Lower the closed jaw onto the wire and keep it closed: no rising edge, no catch.
    pos, rot = _jaw_at_grasp(env)
    for _ in range(25):
        env.step(pose_vector(pos, rot, 1.0))
    assert not u.needle_grasped
    # Open, then close: caught.
    env.step(pose_vector(pos, rot, 0.0))
    for _ in range(3):
        env.step(pose_vector(pos, rot, 0.0))
    env.step(pose_vector(pos, rot, 1.0))
    assert u.needle_grasped


@pytest.mark.parametrize("tilt_deg", [-20, -10, 10, 20])
def test_a_jaw_s_seat_never_pushes_the_lying_needle_into_the_tissue(tilt_deg):
    """A jaw tilted about its face normal seats the wire by turning the needle about where it crosses the jaw;
    one way that turn would put the needle's end into the pad. The seat catches the needle only where it moves
    no point of it more than LODGED_CAPTURE_TOLERANCE into the tissue: otherwise the jaw closes beside it."""
    from lerobot_suture.sim.grasp import LODGED_CAPTURE_TOLERANCE
    from lerobot_suture.sim.needle_capture import seat_needle

    env = make()
    env.reset(seed=0)
    u = env.unwrapped
    grasp = u._grasp
    pos, rot = jaw_holding(*u.needle_pose(), *grasp_transform(GRASP_ANGLE, 0.0, 0.0))
    rot = rot @ matrix_from_rotvec(np.radians(tilt_deg) * np.array([0.0, 1.0, 0.0]))
    for _ in range(30):
        env.step(pose_vector(pos, rot, 0.0))
    jaw_pos, jaw_rot = grasp._arm.jaw_pose(u.data)
    centre, rotation = u.needle_pose()
    seated = seat_needle(jaw_rot.T @ (centre - jaw_pos), jaw_rot.T @ rotation, 0.5 * grasp.wire_diameter)
    assert seated is not None  # the seat rule alone would catch it
    arc = needle_arc_points(7)
    seated_depth = grasp._pad_depth(u.data, jaw_pos + (seated.position + arc @ seated.rotation.T) @ jaw_rot.T)
    env.step(pose_vector(pos, rot, 1.0))
    assert u.needle_grasped == (seated_depth <= LODGED_CAPTURE_TOLERANCE), seated_depth
    centre, rotation = u.needle_pose()
    assert grasp._pad_depth(u.data, centre + arc @ rotation.T) <= LODGED_CAPTURE_TOLERANCE


def test_a_grasp_off_the_ranges_is_held_but_is_no_success():
    env = make()
    env.reset(seed=1)
    u = env.unwrapped
    pos, rot = jaw_holding(*u.needle_pose(), *grasp_transform(GRASP_ANGLE - math.radians(20), 0.0, 0.0))
    for _ in range(30):
        env.step(pose_vector(pos, rot, 0.0))
    _, _, terminated, _, info = env.step(pose_vector(pos, rot, 1.0))
    assert u.needle_grasped and not terminated
    assert abs(info["grasp_parameters"][0] - (GRASP_ANGLE - math.radians(20))) < math.radians(2)
    up = pos + 0.01 * u.phantom_rotation[:, 2]
    for _ in range(10):
        _, _, terminated, _, info = env.step(pose_vector(up, rot, 1.0))
    assert u.needle_clearance > LIFT_HEIGHT and not terminated and not info["is_success"]


def test_the_expert_picks_up_the_needle_on_every_seed():
    env = make()
    lengths = []
    for seed in range(8):
        steps = run_expert(env, seed)
        assert steps[-1].info["is_success"], seed
        lengths.append(len(steps))
    assert max(lengths) < TASKS["pickup"].max_episode_steps // 2


@pytest.mark.parametrize("scenario", TASKS["pickup"].scenarios)
def test_every_scenario_of_pickup_happens_and_the_expert_still_picks_up(scenario):
    env = make(scenario=scenario)
    steps = run_expert(env, seed=2)
    u = env.unwrapped
    assert steps[-1].info["is_success"], scenario
    if scenario != "nominal":
        assert any(s.info["perturbed"] for s in steps)
    if scenario == "needle_drop":
        assert u._grasp.captures == 2  # lost while being lifted, picked up again
    if scenario == "phantom_servo":
        # The needle rode on the phantom as it glided: still where it lay on it.
        assert steps[0].info["needle_tip_pos"] is not None
        first = steps[0].info["needle_tip_pos"]
        assert np.linalg.norm(u.needle_tip_pos - first) > 0.002


def test_insertion_episodes_are_those_of_before_the_task_family():
    """Trajectories of the default task, recorded from the code before `task=` existed (state only)."""
    expected = {
        ("nominal", 0): (56, [0.012221808693693187, -0.005437395390306009, 0.012327759614065365]),
        ("nominal", 7): (56, [0.011647972416497883, 0.010580734106706858, 0.012321987805566665]),
        ("needle_drop", 1): (100, [-0.007435953880918917, 0.010980604522425635, 0.010368068564702399]),
    }
    for (scenario, seed), (length, tip) in expected.items():
        env = gym.make(ENV_ID, obs_type="pixels_agent_pos", scenario=scenario, disable_env_checker=True)
        steps = run_expert(env, seed)
        assert len(steps) == length, (scenario, seed)
        np.testing.assert_allclose(steps[-1].info["needle_tip_pos"], tip, rtol=0, atol=1e-12)
        env.close()
