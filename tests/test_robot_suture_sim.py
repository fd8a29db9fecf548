"""The simulated arm as a LeRobot robot (``lerobot_robot_suture``): plugin discovery, features, the one
simulation core, episode announcements, the clock and the trace. The commands themselves run in
``test_robot_cli.py``."""

import importlib.metadata
import json
import logging
import time

import gymnasium as gym
import numpy as np
import pytest
from lerobot.configs import FeatureType
from lerobot.datasets import aggregate_pipeline_dataset_features, create_initial_features
from lerobot.processor import make_default_processors
from lerobot.robots import RobotConfig, make_robot_from_config
from lerobot.teleoperators import TeleoperatorConfig
from lerobot.utils.feature_utils import combine_feature_dicts, dataset_to_policy_features
from lerobot.utils.import_utils import register_third_party_plugins

import lerobot_suture
from lerobot_suture.datasets import features as expert_features
from lerobot_suture.registration import MAX_EPISODE_STEPS

register_third_party_plugins()  # as every LeRobot command does at start-up

from lerobot_robot_suture import POSE_FEATURES, SutureSim, SutureSimConfig  # noqa: E402
from lerobot_teleoperator_suture import SutureGamepad, SutureKeyboard  # noqa: E402

SIZE = 32


@pytest.fixture
def robot():
    robot = SutureSim(SutureSimConfig(seed=7, image_size=SIZE, clock="fast"))
    robot.connect()
    yield robot
    if robot.is_connected:
        robot.disconnect()


def _pose_action(vector) -> dict:
    return {name: float(v) for name, v in zip(POSE_FEATURES, vector, strict=True)}


def test_lerobot_start_up_registers_the_robot_and_its_teleoperators():
    assert importlib.metadata.distribution("lerobot_robot_suture").metadata["Name"] == "lerobot_robot_suture"
    assert RobotConfig.get_choice_class("suture_sim") is SutureSimConfig
    assert TeleoperatorConfig.get_choice_class("suture_keyboard").__name__ == "SutureKeyboardConfig"
    assert TeleoperatorConfig.get_choice_class("suture_gamepad").__name__ == "SutureGamepadConfig"
    assert isinstance(make_robot_from_config(SutureSimConfig()), SutureSim)
    # LeRobot's factory finds each device class from its config's name (make_device_from_device_class).
    assert SutureKeyboard.name == "suture_keyboard" and SutureGamepad.name == "suture_gamepad"
    with pytest.raises(ValueError, match="`clock` must be one of"):
        SutureSimConfig(clock="slow")


def test_recorded_features_are_the_expert_data_s():
    """LeRobot's record builds the dataset's features from the robot's (default processors): the keys,
    dtypes and shapes of the expert data, the pose's names with LeRobot's `.pos` suffix; and the policy
    features (what a policy config holds) are the expert data's."""
    robot = SutureSim(SutureSimConfig(image_size=96))
    teleop_action, _, robot_observation = make_default_processors()
    recorded = combine_feature_dicts(
        aggregate_pipeline_dataset_features(
            teleop_action, create_initial_features(action=robot.action_features), use_videos=True
        ),
        aggregate_pipeline_dataset_features(
            robot_observation,
            create_initial_features(observation=robot.observation_features),
            use_videos=True,
        ),
    )
    expert = expert_features.dataset_features("pixels_agent_pos", 96, video=True)
    keys = [expert_features.IMAGE_KEY, expert_features.STATE_KEY, expert_features.ACTION_KEY]
    assert set(recorded) == set(keys)
    for key in keys:
        assert recorded[key]["dtype"] == expert[key]["dtype"]
        assert tuple(recorded[key]["shape"]) == tuple(expert[key]["shape"])
    assert recorded[expert_features.STATE_KEY]["names"] == [f"{n}.pos" for n in expert_features.POSE_NAMES]
    assert recorded[expert_features.ACTION_KEY]["names"] == POSE_FEATURES
    policy = dataset_to_policy_features(recorded)
    assert policy == {k: v for k, v in dataset_to_policy_features(expert).items() if k in keys}
    assert policy[expert_features.IMAGE_KEY].type is FeatureType.VISUAL
    # lerobot-rollout keeps camera tuples and scalar features named *.pos / *.vel: all of ours.
    kept = {k for k, v in robot.observation_features.items() if isinstance(v, tuple) or k.endswith(".pos")}
    assert kept == set(robot.observation_features)


def test_the_robot_runs_the_env_s_simulation(robot):
    """The robot is the registered env: the same observation after reset and after each step."""
    env = gym.make(lerobot_suture.ENV_ID, disable_env_checker=True, image_size=SIZE)
    obs, _ = env.reset(seed=7)
    observation = robot.get_observation()
    assert set(observation) == set(robot.observation_features)
    assert observation["endoscope"].shape == (SIZE, SIZE, 3) and observation["endoscope"].dtype == np.uint8
    np.testing.assert_array_equal(observation["endoscope"], obs["pixels"]["endoscope"])
    np.testing.assert_allclose([observation[n] for n in POSE_FEATURES], obs["agent_pos"])
    target = obs["agent_pos"].astype(np.float64) + np.r_[0.002, -0.001, 0.0, np.zeros(7)]
    target[9] = 1.0
    for _ in range(3):
        sent = robot.send_action(_pose_action(target))
        obs, *_ = env.step(target)
    np.testing.assert_array_equal(robot.get_observation()["endoscope"], obs["pixels"]["endoscope"])
    np.testing.assert_allclose(robot.measured_pose(), obs["agent_pos"])
    np.testing.assert_allclose([sent[n] for n in POSE_FEATURES], target)
    assert robot.scene_steps == 3 and robot.needle_tip.shape == (3,)
    far = target.copy()
    far[0] = 1.0  # outside the workspace: the env clips it, and send_action says so
    assert robot.send_action(_pose_action(far))["x.pos"] == pytest.approx(0.05)
    env.close()


def test_calibrate_is_a_no_op_that_says_so_and_commands_are_refused(robot, caplog):
    with caplog.at_level(logging.INFO):
        robot.calibrate()
    assert "nothing to calibrate" in caplog.text and robot.is_calibrated
    with pytest.raises(ValueError, match="suture_keyboard"):
        robot.send_action({"delta_x": 1.0, "delta_y": 0.0, "delta_z": 0.0, "gripper": 1.0})
    with pytest.raises(ValueError, match="lacks"):
        robot.send_action({"x.pos": 0.0})
    robot.disconnect()
    assert not robot.is_connected
    with pytest.raises(Exception, match="not connected"):
        robot.get_observation()


def test_lerobot_s_episodes_reset_the_scene(robot):
    """Dataset episode N plays the scene of seed + N, fresh; after an episode, the next scene is held."""
    from lerobot_suture.lerobot_shim import EpisodeAware, episode

    assert isinstance(robot, EpisodeAware)
    hold = _pose_action(robot.measured_pose())
    with episode(robot, 0):
        assert (robot.scene_seed, robot.scene_count) == (7, 1)  # the scene of connect is fresh: kept
        robot.send_action(hold)
        robot.send_action(hold)
    assert (robot.scene_seed, robot.scene_steps, robot.holding) == (8, 0, True)
    robot.send_action(hold)  # LeRobot's reset-phase motions are not executed
    assert robot.scene_steps == 0
    robot.start_episode(1)
    assert (robot.scene_seed, robot.holding, robot.scene_count) == (8, False, 2)
    robot.send_action(hold)
    robot.end_episode()
    assert robot.scene_seed == 9
    robot.start_episode(1)  # re-recorded: the same scene again
    assert (robot.scene_seed, robot.scene_steps) == (8, 0)
    robot.start_episode(5)  # a resumed dataset with five episodes
    assert robot.scene_seed == 12
    env = gym.make(lerobot_suture.ENV_ID, disable_env_checker=True, image_size=SIZE)
    np.testing.assert_allclose(robot.measured_pose(), env.reset(seed=12)[0]["agent_pos"])
    env.close()
    robot.disconnect()
    with pytest.raises(Exception, match="not connected"):
        robot.start_episode(2)


def test_realtime_clock_holds_a_step_to_the_control_period():
    for clock, low, high in (("realtime", 0.29, 1.5), ("fast", 0.0, 0.25)):
        robot = SutureSim(SutureSimConfig(image_size=16, clock=clock))
        robot.connect()
        hold = _pose_action(robot.measured_pose())
        start = time.perf_counter()
        for _ in range(4):  # the first step runs at once, each next one 0.1 s after the one before
            robot.send_action(hold)
        elapsed = time.perf_counter() - start
        robot.disconnect()
        assert low <= elapsed <= high, (clock, elapsed)


def test_trace_has_a_line_per_executed_step(tmp_path):
    path = tmp_path / "trace" / "steps.jsonl"
    robot = SutureSim(SutureSimConfig(seed=3, image_size=16, clock="fast", trace_path=path))
    robot.connect()
    hold = _pose_action(robot.measured_pose())
    robot.send_action(hold)
    robot.end_episode()
    robot.send_action(hold)  # held: not executed, not traced
    robot.start_episode(1)
    robot.send_action(hold)
    tip = robot.needle_tip
    robot.disconnect()
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    assert [(line["seed"], line["step"]) for line in lines] == [(3, 1), (4, 1)]
    np.testing.assert_allclose(lines[-1]["needle_tip"], tip)
    assert {"action", "pose", "is_success", "throw_over", "needle_in_tissue", "needle_grasped"} <= set(
        lines[0]
    )


@pytest.mark.parametrize("episode_end", ["hold", "continue"])
def test_at_the_episode_s_end_the_arm_holds_or_continues(episode_end):
    """``hold`` stops executing once the env's episode has ended (its 10 s limit here), as lerobot-eval stops
    an env; ``continue`` keeps following the commands; a new scene starts over either way."""
    robot = SutureSim(SutureSimConfig(seed=3, image_size=SIZE, clock="fast", episode_end=episode_end))
    robot.connect()
    try:
        hold = _pose_action(robot.measured_pose())
        for _ in range(MAX_EPISODE_STEPS + 5):
            robot.send_action(hold)
        expected = MAX_EPISODE_STEPS if episode_end == "hold" else MAX_EPISODE_STEPS + 5
        assert robot.scene_steps == expected
        assert robot.scene_over == (episode_end == "hold")
        robot.reset_scene(4)
        robot.send_action(_pose_action(robot.measured_pose()))
        assert robot.scene_steps == 1 and not robot.scene_over
    finally:
        robot.disconnect()


def test_an_unknown_episode_end_is_refused_with_the_choices():
    with pytest.raises(ValueError, match=r"`episode_end` must be one of \('continue', 'hold'\)"):
        SutureSimConfig(episode_end="stop")


def test_the_pickup_task_runs_on_the_robot():
    """``--robot.task=pickup``: the scene of the pickup env, its instruction as the robot's task."""
    from lerobot_suture.sim.tasks import TASKS

    robot = SutureSim(SutureSimConfig(task="pickup", seed=3, image_size=SIZE, clock="fast"))
    robot.connect()
    try:
        env = gym.make(TASKS["pickup"].gym_id, disable_env_checker=True, image_size=SIZE)
        obs, _ = env.reset(seed=3)
        np.testing.assert_array_equal(robot.get_observation()["endoscope"], obs["pixels"]["endoscope"])
        assert robot.task == TASKS["pickup"].instruction
        assert robot.get_observation()["jaw.pos"] == pytest.approx(0.0, abs=1e-6)  # the jaw starts open
        env.close()
    finally:
        robot.disconnect()
    with pytest.raises(ValueError, match="does not apply to task 'pickup'"):
        SutureSimConfig(task="pickup", scenario="phantom_moved_after_insertion")
