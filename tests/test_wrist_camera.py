"""The wrist camera: opt-in on the env, the robot and the recorder; an env without it is unchanged (its LeRobot
env-config flag is tested with the others in `test_env_plugin.py`)."""

from __future__ import annotations

import numpy as np
import pytest

from lerobot_suture.expert import ScriptedExpert
from lerobot_suture.sim.suture_env import SutureEnv
from lerobot_suture.sim.wrist_camera import WRIST_CAMERA


def _expert_run(env: SutureEnv, steps: int) -> list[dict]:
    obs, _ = env.reset(seed=3)
    expert = ScriptedExpert()
    expert.reset(env)
    out = [obs]
    for _ in range(steps):
        obs, *_ = env.step(expert.act(env))
        out.append(obs)
    return out


def test_the_wrist_camera_leaves_the_episode_as_it_was_and_sees_the_instrument_move():
    plain, wrist = SutureEnv(image_size=32), SutureEnv(image_size=32, wrist_camera=True)
    try:
        with pytest.raises(KeyError):
            plain.model.camera(WRIST_CAMERA)
        a, b = _expert_run(plain, 30), _expert_run(wrist, 30)
        assert set(b[0]["pixels"]) == {"endoscope", "wrist"} and set(a[0]["pixels"]) == {"endoscope"}
        assert (
            wrist.observation_space["pixels"]["wrist"].shape == b[0]["pixels"]["wrist"].shape == (32, 32, 3)
        )
        for x, y in zip(a, b, strict=True):  # the same physics, the same endoscope images
            np.testing.assert_array_equal(x["agent_pos"], y["agent_pos"])
            np.testing.assert_array_equal(x["pixels"]["endoscope"], y["pixels"]["endoscope"])
        views = [o["pixels"]["wrist"].astype(int) for o in b]
        assert not np.array_equal(views[0], b[0]["pixels"]["endoscope"])
        assert np.abs(views[-1] - views[0]).mean() > 5  # the instrument moved, and its view with it
    finally:
        plain.close()
        wrist.close()


def test_a_wrist_camera_needs_an_observation_with_images():
    with pytest.raises(ValueError, match="`wrist_camera` adds an image"):
        SutureEnv(obs_type="state", wrist_camera=True)


def test_the_robot_reports_the_wrist_image_as_a_second_camera():
    from lerobot_robot_suture import SutureSim, SutureSimConfig

    robot = SutureSim(SutureSimConfig(seed=7, image_size=32, clock="fast", wrist_camera=True))
    robot.connect()
    try:
        assert set(robot.cameras) == {"endoscope", "wrist"}  # LeRobot sizes its image writers by them
        assert robot.observation_features["wrist"] == (32, 32, 3)
        first = robot.get_observation()["wrist"]
        pose = {
            k: first_pose + 0.01 * (k == "z.pos")
            for k, first_pose in robot.get_observation().items()
            if k.endswith(".pos")
        }
        for _ in range(5):
            robot.send_action(pose)
        assert first.shape == (32, 32, 3) and not np.array_equal(robot.get_observation()["wrist"], first)
    finally:
        robot.disconnect()
    assert "wrist" not in SutureSim(SutureSimConfig()).observation_features


def test_a_recording_with_the_wrist_camera_stores_it_as_video_and_resumes_only_with_it(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_suture.datasets.features import WRIST_IMAGE_KEY
    from lerobot_suture.datasets.record import record
    from lerobot_suture.datasets.record_config import RecordConfig

    root = tmp_path / "data"
    cfg = dict(repo_id="suture-tests/wrist", root=str(root), image_size=32, num_episodes=1, val_fraction=0.0)
    record(RecordConfig(**cfg, wrist_camera=True))
    dataset = LeRobotDataset("suture-tests/wrist", root=root)
    assert dataset.meta.features[WRIST_IMAGE_KEY]["dtype"] == "video"
    assert dataset[0][WRIST_IMAGE_KEY].shape == (3, 32, 32)
    assert "--wrist_camera=true" in RecordConfig(**cfg, wrist_camera=True).command()
    with pytest.raises(ValueError, match="--wrist_camera=true"):
        record(RecordConfig(**{**cfg, "num_episodes": 2}, resume=True))
    with pytest.raises(ValueError, match="--obs_type=pixels_agent_pos"):
        RecordConfig(**cfg, obs_type="state", wrist_camera=True)


def test_a_policy_that_reads_the_wrist_camera_gets_an_env_that_renders_it():
    from types import SimpleNamespace

    import gymnasium as gym
    from lerobot.configs import FeatureType, PolicyFeature

    from lerobot_suture.runtime.policy import WRIST_IMAGE, env_kwargs_for_policy

    image = PolicyFeature(type=FeatureType.VISUAL, shape=(3, 32, 32))
    state = PolicyFeature(type=FeatureType.STATE, shape=(10,))
    both = {"observation.images.endoscope": image, WRIST_IMAGE: image, "observation.state": state}
    kwargs = env_kwargs_for_policy(SimpleNamespace(input_features=both))
    assert kwargs == {"obs_type": "pixels_agent_pos", "image_size": 32, "wrist_camera": True}
    env = gym.make("lerobot_suture/NeedlePickup-v0", disable_env_checker=True, **kwargs)
    obs, _ = env.reset(seed=0)
    env.close()
    assert {name: obs["pixels"][name].shape for name in obs["pixels"]} == {
        "endoscope": (32, 32, 3),
        "wrist": (32, 32, 3),
    }
    endoscope_only = {k: v for k, v in both.items() if k != WRIST_IMAGE}
    assert "wrist_camera" not in env_kwargs_for_policy(SimpleNamespace(input_features=endoscope_only))
    small_wrist = {**both, WRIST_IMAGE: PolicyFeature(type=FeatureType.VISUAL, shape=(3, 16, 16))}
    with pytest.raises(ValueError, match="one size"):
        env_kwargs_for_policy(SimpleNamespace(input_features=small_wrist))
