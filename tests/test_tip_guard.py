"""The CBF on the robot path: ``TipGuard`` from kinematics alone, and the ``suture_cbf`` processor step."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lerobot_suture.safety.cbf import ellipsoid_h
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.safety.tip_guard import PHASE_ACTIVE, PHASE_DONE, PHASE_IDLE, GraspModel, TipGuard, Wound
from lerobot_suture.sim.geometry import matrix_from_rotvec, pose_vector

ENTRY = np.array([-0.009, 0.0, 0.0])
EXIT = np.array([0.009, 0.0, 0.0])
NORMAL = np.array([0.0, 0.0, 1.0])
WOUND = Wound(ENTRY, EXIT, NORMAL)
GRASP = GraspModel()
DT = 0.1


def jaw_pose_with_tip_at(tip: np.ndarray, rotation: np.ndarray, jaw: float = 0.88) -> np.ndarray:
    """The (10,) pose that puts the modelled needle tip at ``tip`` with jaw orientation ``rotation``."""
    return pose_vector(tip - rotation @ GRASP.tip_in_jaw(), rotation, jaw)


def tip_of(pose: np.ndarray) -> np.ndarray:
    from lerobot_suture.sim.geometry import matrix_from_rot6

    return pose[:3] + matrix_from_rot6(pose[3:9]) @ GRASP.tip_in_jaw()


def tightened_h(point: np.ndarray, cbf: CBFConfig) -> float:
    center, rotation = WOUND.ellipsoid_frame()
    return float(ellipsoid_h(point, center, cbf.semi_axes, rotation)) - cbf.margin_level


def test_wound_and_grasp_reject_bad_values():
    with pytest.raises(ValueError, match="entry_point"):
        Wound([0.0, np.nan, 0.0], EXIT, NORMAL)
    with pytest.raises(ValueError, match="surface_normal"):
        Wound(ENTRY, EXIT, [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="apart"):
        Wound(ENTRY, ENTRY, NORMAL)
    with pytest.raises(ValueError, match="roll"):
        GraspModel(roll=2.0)
    with pytest.raises(ValueError, match="held_jaw_range"):
        TipGuard(held_jaw_range=(0.9, 0.5))


def test_no_wound_passes_the_target_unchanged():
    guard = TipGuard()
    pose = jaw_pose_with_tip_at(np.zeros(3), np.eye(3))
    target = pose + np.r_[0.03, 0, 0, np.zeros(7)]
    out, result = guard.filter_target(pose, target, None, GRASP, DT)
    np.testing.assert_array_equal(out, target)
    assert not result.active and guard.phase == PHASE_IDLE


def test_bad_poses_raise_a_clear_error():
    guard = TipGuard()
    pose = jaw_pose_with_tip_at(np.zeros(3), np.eye(3))
    with pytest.raises(ValueError, match="target_pose"):
        guard.filter_target(pose, np.full(10, np.nan), WOUND, GRASP, DT)
    parallel = pose.copy()
    parallel[6:9] = parallel[3:6]
    with pytest.raises(ValueError, match="parallel"):
        guard.filter_target(pose, parallel, WOUND, GRASP, DT)


def test_phase_follows_the_measured_jaw_and_the_needle_against_the_tissue():
    guard = TipGuard()
    above = jaw_pose_with_tip_at(np.array([0.0, 0.0, 0.004]), np.eye(3))
    guard.filter_target(above, above, WOUND, GRASP, DT)
    assert guard.phase == PHASE_ACTIVE
    # The jaw reads fully closed: it lost the needle, and the throw's guard ends.
    lost = above.copy()
    lost[9] = 1.0
    guard.filter_target(lost, lost, WOUND, GRASP, DT)
    assert guard.phase == PHASE_DONE
    # A new throw starts over.
    guard.filter_target(above, above, Wound(ENTRY, EXIT, NORMAL, throw_index=1), GRASP, DT)
    assert guard.phase == PHASE_ACTIVE


@settings(max_examples=300, deadline=None)
@given(
    start=st.tuples(*[st.floats(-1.0, 1.0)] * 3),
    rotvec=st.tuples(*[st.floats(-3.0, 3.0)] * 3),
    target_pos=st.tuples(*[st.floats(-5.0, 5.0)] * 3),
    target_rotvec=st.tuples(*[st.floats(-3.1, 3.1)] * 3),
    scale=st.floats(1e-4, 1.0),
)
def test_the_commanded_tip_end_point_stays_in_the_tightened_set(
    start, rotvec, target_pos, target_rotvec, scale
):
    """Any target, from any tip inside the tightened set: the tip's commanded end point stays inside it."""
    cbf = CBFConfig(enabled=True)
    center, rotation = WOUND.ellipsoid_frame()
    direction = np.asarray(start)
    if np.linalg.norm(direction) < 1e-6:
        direction = np.array([1.0, 0.0, 0.0])
    # A point of the tightened ellipsoid, inside it by a random fraction.
    tight_axes = cbf.semi_axes * np.sqrt(1.0 - cbf.margin_level)
    tip = center + rotation @ (tight_axes * direction / np.linalg.norm(direction) * 0.999 * scale)
    pose = jaw_pose_with_tip_at(tip, matrix_from_rotvec(np.asarray(rotvec)))
    target = pose_vector(np.asarray(target_pos) * 0.01, matrix_from_rotvec(np.asarray(target_rotvec)), 1.0)
    guard = TipGuard(cbf)
    out, result = guard.filter_target(pose, target, WOUND, GRASP, DT)
    assert result.active
    assert tightened_h(tip_of(out), cbf) >= -1e-9


def test_the_env_wrapper_and_the_step_share_one_guard():
    from lerobot_suture.safety.cbf_wrapper import CBFActionWrapper
    from lerobot_suture.sim.suture_env import SutureEnv

    env = CBFActionWrapper(SutureEnv(obs_type="state"))
    assert isinstance(env._guard, TipGuard)
    env.close()


# ---------------------------------------------------------------- the processor step and the robot path
lerobot_robot_suture = pytest.importorskip("lerobot_robot_suture")


def test_step_is_registered_and_round_trips_its_config(tmp_path):
    from lerobot.processor import ProcessorStepRegistry, RobotProcessorPipeline
    from lerobot.processor.converters import (
        robot_action_observation_to_transition,
        transition_to_robot_action,
    )
    from lerobot_robot_suture.cbf_step import SutureCBFStep

    assert ProcessorStepRegistry.get("suture_cbf") is SutureCBFStep
    step = SutureCBFStep(cbf={"alpha": 3.0, "enabled": True}, wound=[*ENTRY, *EXIT, *NORMAL])
    again = SutureCBFStep(**step.get_config())
    assert again.get_config() == step.get_config()
    pipeline = RobotProcessorPipeline(
        steps=[step],
        to_transition=robot_action_observation_to_transition,
        to_output=transition_to_robot_action,
    )
    pipeline.save_pretrained(tmp_path)
    loaded = RobotProcessorPipeline.from_pretrained(
        tmp_path,
        config_filename=next(p.name for p in tmp_path.glob("*.json")),
        to_transition=robot_action_observation_to_transition,
        to_output=transition_to_robot_action,
    )
    assert loaded.steps[0].get_config() == step.get_config()


def test_step_reads_the_registration_and_names_missing_features():
    from lerobot_robot_suture.cbf_step import GRASP_FEATURES, THROW_FEATURE, WOUND_FEATURES, SutureCBFStep
    from lerobot_robot_suture.config_suture_sim import POSE_FEATURES

    step = SutureCBFStep()
    pose = jaw_pose_with_tip_at(np.array([0.0, 0.0, 0.004]), np.eye(3))
    observation = dict(zip(POSE_FEATURES, pose.tolist(), strict=True))
    action = dict(zip(POSE_FEATURES, (pose + np.r_[0.0, 0.0, -0.05, np.zeros(7)]).tolist(), strict=True))
    # No registration and no configured wound: nothing to guard.
    step(dict(action=action, observation=observation))
    assert step.phase == PHASE_IDLE
    observation.update(zip(WOUND_FEATURES, [*ENTRY, *EXIT, *NORMAL], strict=True))
    observation.update(
        {THROW_FEATURE: 0.0, **dict(zip(GRASP_FEATURES, (GRASP.angle, 0.0, 0.0), strict=True))}
    )
    from lerobot.processor.converters import robot_action_observation_to_transition

    out = step(robot_action_observation_to_transition((action, observation)))
    assert step.phase == PHASE_ACTIVE and step.last_result.intervened
    sent = np.array([out["action"][k] for k in POSE_FEATURES])
    assert tightened_h(tip_of(sent), step.cbf) >= -1e-9
    with pytest.raises(ValueError, match="jaw.pos"):
        del observation["jaw.pos"]
        step(robot_action_observation_to_transition((action, observation)))


@pytest.mark.parametrize(
    "faults",
    [{}, {"observation_latency": 3}, {"command_latency": 3}],
    ids=["none", "observation3", "command3"],
)
def test_robot_path_attacks_never_leave_the_set(faults):
    """One episode of every family through the pipeline, with the robot's ``faults``."""
    from lerobot_robot_suture.attacks import make_robot_path, run_robot_attack_episode
    from lerobot_robot_suture.faults import FaultConfig

    from lerobot_suture.experiments.cbf_attacks import FAMILIES

    robot_path = make_robot_path(image_size=32, faults=FaultConfig(**faults))
    try:
        episodes = [run_robot_attack_episode(robot_path, family, seed=11) for family in FAMILIES]
    finally:
        robot_path[0].disconnect()
    assert sum(e.active_steps for e in episodes) > 50
    assert sum(e.interventions for e in episodes) > 0
    assert all(e.violation_steps == 0 for e in episodes), [(e.family, e.h_min) for e in episodes]


def test_expert_throws_on_the_robot_path_are_left_alone():
    """Minimal intervention: the scripted expert's nominal throws pass the step unchanged and succeed."""
    from lerobot_robot_suture.attacks import make_robot_path
    from lerobot_robot_suture.config_suture_sim import POSE_FEATURES

    from lerobot_suture.expert import ScriptedExpert

    robot, pipeline, step = make_robot_path(image_size=32)
    try:
        for seed in range(3):
            robot.reset_scene(seed)
            pipeline.reset()
            expert = ScriptedExpert()
            expert.reset(robot.env)
            active = 0
            while not robot.scene_over:
                action = dict(zip(POSE_FEATURES, expert.act(robot.env).tolist(), strict=True))
                robot.send_action(pipeline((action, robot.get_observation())))
                active += int(step.last_result.active)
                assert not step.last_result.intervened
            assert robot.last_info["is_success"] and active > 10
    finally:
        robot.disconnect()
