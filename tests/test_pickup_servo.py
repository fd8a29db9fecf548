"""The scripted pick-up (``sim.pickup_servo``): the needle estimated flat on the surface from where the jaw let go,
a search across the faces after a miss, the grasp an insertion starts from on the real env, and the chain written
with ``--scripted_pick_up=true`` picking the laid-down needle up with no learned action."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from lerobot.envs.utils import preprocess_observation
from lerobot_policy_suture_chain.assemble import ChainCommandConfig, write_chain
from test_regrasp_servo import _conditioned_act

from lerobot_suture.expert import ScriptedExpert
from lerobot_suture.runtime.policy import load_policy
from lerobot_suture.sim.extraction import REGRASP_ANGLE
from lerobot_suture.sim.geometry import grasp_transform, needle_in_world, pose_vector, rotation_about_x
from lerobot_suture.sim.pickup import grasp_ready_for_throw
from lerobot_suture.sim.pickup_servo import (
    SURFACE_NORMAL,
    WIRE_RADIUS,
    NeedleRelease,
    PickupServo,
    PickupServoConfig,
    carried_by_phantom,
    marks_frame,
    resting_needle,
    search_offset,
)
from lerobot_suture.sim.relative_actions import measured_jaw
from lerobot_suture.sim.subtasks import JAW_INDEX
from lerobot_suture.sim.task import GRASP_ANGLE
from lerobot_suture.sim.wound_marks import MARKS_DIM

RUNNING_SUTURE_ID = "lerobot_suture/RunningSuture-v0"
SEED = 37_000_002  # a nominal test seed of the running-suture cell


def _jaw_down(position, tilt: float = 0.0) -> np.ndarray:
    """A jaw pose (10,) pointing down (z along -world z), tilted ``tilt`` rad about its x axis, open."""
    rotation = rotation_about_x(np.pi) @ rotation_about_x(tilt)
    return pose_vector(np.asarray(position, dtype=np.float64), rotation, 0.0)


def test_the_resting_needle_lies_flat_a_wire_radius_above_the_surface_about_the_held_needle():
    """Flat (its plane's normal into the tissue), its wire's axis a wire radius above the surface, its centre
    where the held needle's was across the surface; a jaw held flat gives back the held needle's in-plane turn."""
    release = _jaw_down([0.002, -0.003, 0.014], tilt=0.2)
    release_pos, release_rot = measured_jaw(release)
    centre, rotation = resting_needle(release_pos, release_rot, REGRASP_ANGLE, surface_height=0.01)
    held_centre, held_rot = needle_in_world(
        release_pos, release_rot, *grasp_transform(REGRASP_ANGLE, 0.0, 0.0)
    )
    np.testing.assert_allclose(rotation[:, 2], -SURFACE_NORMAL, atol=1e-12)
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    assert centre[2] == pytest.approx(0.01 + WIRE_RADIUS)
    np.testing.assert_allclose(centre[:2], held_centre[:2], atol=1e-12)
    x_flat = held_rot[:2, 0] / np.linalg.norm(held_rot[:2, 0])
    np.testing.assert_allclose(rotation[:2, 0], x_flat, atol=1e-12)
    flat_release = measured_jaw(_jaw_down([0.002, -0.003, 0.0104]))
    centre, rotation = resting_needle(*flat_release, GRASP_ANGLE, surface_height=0.01)
    expected = needle_in_world(*flat_release, *grasp_transform(GRASP_ANGLE, 0.0, 0.0))
    np.testing.assert_allclose(centre, expected[0], atol=1e-12)
    np.testing.assert_allclose(rotation, expected[1], atol=1e-12)


def test_a_pose_on_the_phantom_follows_the_marks_rigidly():
    """The marks glide and turn about the vertical: a pose on the phantom moves with them, keeping its place in the
    marks' frame; unmoved marks leave it where it is."""
    from lerobot_suture.sim.geometry import rotation_about_z

    marks = np.array([-0.008, 0.001, 0.01, 0.008, 0.001, 0.01])
    pose = (np.array([0.003, -0.004, 0.0104]), rotation_about_z(0.3) @ rotation_about_x(np.pi))
    same = carried_by_phantom(pose, marks, marks)
    np.testing.assert_allclose(same[0], pose[0], atol=1e-15)
    np.testing.assert_allclose(same[1], pose[1], atol=1e-15)
    turn, shift = rotation_about_z(0.2), np.array([0.004, -0.002, 0.001])
    moved = np.concatenate([turn @ marks[:3] + shift, turn @ marks[3:] + shift])
    position, rotation = carried_by_phantom(pose, marks, moved)
    np.testing.assert_allclose(position, turn @ pose[0] + shift, atol=1e-12)
    np.testing.assert_allclose(rotation, turn @ pose[1], atol=1e-12)
    origin, frame = marks_frame(moved)
    np.testing.assert_allclose(frame[:, 2], SURFACE_NORMAL)
    np.testing.assert_allclose(origin, 0.5 * (moved[:3] + moved[3:]))


def test_the_search_alternates_across_the_faces_by_growing_steps():
    assert [search_offset(m, 0.001) for m in range(5)] == pytest.approx([0, 0.001, -0.001, 0.002, -0.002])


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("approach_height", 0.0, "approach_height"),
        ("descend_speed", float("nan"), "descend_speed"),
        ("settle_steps", -1, "settle_steps"),
        ("attempts", 0, "attempts"),
        ("search_step", 0.0025, "search_step"),
        ("search_step", 0.0, "search_step"),
        ("holding_below", 0.4, "closed_above < holding_below"),
    ],
)
def test_the_config_refuses_what_cannot_pick_up(field, value, match):
    with pytest.raises(ValueError, match=match):
        PickupServoConfig(**{field: value})


def test_a_servo_whose_closings_miss_searches_across_the_faces_and_stops_after_its_attempts():
    """A kinematic arm that reaches every target and a jaw that closes fully (nothing between its faces): each
    closing aims at the next search offset along the grasp's y axis, the servo is done after ``attempts``
    closings, not held, and refuses to act again."""
    config = PickupServoConfig(attempts=3)
    needle = resting_needle(*measured_jaw(_jaw_down([0.0, 0.0, 0.0114])), GRASP_ANGLE, surface_height=0.01)
    marks = np.array([-0.008, 0.0, 0.01, 0.008, 0.0, 0.01])
    servo = PickupServo(needle, marks, config)
    grasp_pos, grasp_rot = servo.grasp
    pose, aims = _jaw_down([0.01, 0.01, 0.03]), []
    for _ in range(600):
        action = servo.act(pose, marks)
        if action[JAW_INDEX] == 1.0 and (not aims or servo.closings > len(aims)):
            aims.append(measured_jaw(action.astype(np.float64))[0])
        pose = np.concatenate([action[:9], [1.0 if action[JAW_INDEX] > 0.5 else 0.0]])
        if servo.done:
            break
    assert servo.done and not servo.held and servo.closings == 3
    offsets = [(aim - grasp_pos) @ grasp_rot[:, 1] for aim in aims]
    assert offsets == pytest.approx([search_offset(m, config.search_step) for m in range(3)], abs=1e-6)
    with pytest.raises(RuntimeError, match="insert policy"):
        servo.act(pose, marks)


def test_the_release_keeps_the_last_held_pose_and_the_angle_its_subtask_holds_at():
    release = NeedleRelease()
    held = _jaw_down([0.0, 0.0, 0.02])
    held[JAW_INDEX] = 0.85
    release.update(held, "lay_down")
    assert release.held_angle == REGRASP_ANGLE
    np.testing.assert_allclose(release.pose[0], held[:3])
    opened = _jaw_down([0.0, 0.0, 0.03])
    release.update(opened, "lay_down")  # open: the needle is let go, the pose stays
    np.testing.assert_allclose(release.pose[0], held[:3])
    release.update(held, "insert")
    assert release.held_angle == GRASP_ANGLE


def _expert_until_pick_up(env, observation):
    """Run the running suture's scripted expert until it begins the first pick-up, the release read as the chain
    reads it."""
    expert = ScriptedExpert(task="running_suture")
    expert.reset(env)
    release = NeedleRelease()
    for _ in range(env.spec.max_episode_steps):
        action = expert.act(env)
        if expert.stage == "pick_up":
            return observation, release
        release.update(observation["agent_pos"], expert.stage)
        observation, _, terminated, truncated, _ = env.step(action)
        assert not (terminated or truncated)
    raise AssertionError("the expert never reached the pick-up")


def test_the_servo_picks_the_laid_down_needle_up_in_the_grasp_a_throw_starts_from():
    """On the real env, after the expert's first throw and lay-down: planned from the release and the marks'
    height alone, the jaw closes once and holds the needle in a grasp an insertion is tested in (the simulator's
    grasp, read here only to judge it)."""
    env = gym.make(RUNNING_SUTURE_ID, obs_type="pixels_agent_pos", marks=True, image_size=32)
    try:
        observation, _ = env.reset(seed=SEED)
        observation, release = _expert_until_pick_up(env, observation)
        assert release.held_angle == REGRASP_ANGLE
        marks = observation["environment_state"][:MARKS_DIM]
        servo = PickupServo(
            resting_needle(*release.pose, release.held_angle, float(marks[[2, 5]].mean())), marks
        )
        for _ in range(200):
            marks = observation["environment_state"][:MARKS_DIM]
            observation, _, terminated, truncated, _ = env.step(servo.act(observation["agent_pos"], marks))
            if servo.done or terminated or truncated:
                break
        base = env.unwrapped
        assert servo.done and servo.held and servo.closings == 1
        assert base.needle_grasped and grasp_ready_for_throw(base.grasp_parameters, base.grasp_reversed)
    finally:
        env.close()


def test_the_chain_scripts_the_pick_up_and_hands_the_held_needle_to_the_insert(tmp_path):
    """`lerobot-suture chain --scripted_pick_up=true` on the real env: the chain's rules follow the expert's first
    throw; once they read the pick-up, the servo gives every action until the jaw holds the needle, and the chain
    then reads the second throw's insert."""
    policy = _conditioned_act(tmp_path / "policy")
    out = write_chain(ChainCommandConfig(output_dir=tmp_path / "chain", policy=policy, scripted_pick_up=True))
    chain, pre, post = load_policy(out)
    assert chain.config.scripted_pick_up
    env = gym.make(RUNNING_SUTURE_ID, obs_type="pixels_agent_pos", marks=True, image_size=32)
    try:
        observation, _ = env.reset(seed=SEED)
        chain.reset()
        expert = ScriptedExpert(task="running_suture")
        expert.reset(env)
        served = 0
        for _ in range(env.spec.max_episode_steps):
            action = post(chain.select_action(pre(preprocess_observation(observation))))[0].numpy()
            if chain.readings[0][0] == "pick_up":
                assert chain.pickups[0] is not None and not chain.pickups[0].done
                served += 1
            elif served:  # the chain's rules read the pick-up over
                break
            else:  # the expert's first throw and lay-down
                action = expert.act(env)
            observation, _, terminated, truncated, _ = env.step(action)
            assert not (terminated or truncated)
        assert chain.readings[0] == ("insert", 1) and served > 10
        assert chain.pickups[0] is None and env.unwrapped.needle_grasped
    finally:
        env.close()
