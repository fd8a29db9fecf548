"""The observations a surgical robot has, beyond the endoscope: the wrist camera and the wound's marks, opt-in on
the env, the robot and the recorder; an env without them is unchanged (their LeRobot env-config flags are tested
with the others in `test_env_plugin.py`)."""

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


def test_the_wound_s_marks_leave_the_episode_as_it_was_and_follow_the_running_suture_s_throws():
    """``marks=True`` adds the current throw's entry and exit marks; everything else of the episode is as without
    them, and on the running suture the marks move to the next pair once a throw is extracted."""
    import gymnasium as gym

    from lerobot_suture.sim.wound_marks import MARKS_KEY

    kwargs = dict(obs_type="pixels_agent_pos", image_size=16, disable_env_checker=True)
    plain = gym.make("lerobot_suture/NeedleInsertion-v0", **kwargs)
    marked = gym.make("lerobot_suture/NeedleInsertion-v0", marks=True, **kwargs)
    runs = []
    for env in (plain, marked):
        obs, _ = env.reset(seed=3)
        expert = ScriptedExpert()
        expert.reset(env.unwrapped)
        run = [obs]
        for _ in range(20):
            obs, *_ = env.step(expert.act(env.unwrapped))
            run.append(obs)
        runs.append(run)
        env.close()
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a["agent_pos"], b["agent_pos"])
        np.testing.assert_array_equal(a["pixels"]["endoscope"], b["pixels"]["endoscope"])
        assert MARKS_KEY not in a and b[MARKS_KEY].shape == (6,) and b[MARKS_KEY].dtype == np.float32
    assert marked.observation_space[MARKS_KEY].shape == (6,)
    with pytest.raises(ValueError, match="pixels_agent_pos"):
        gym.make("lerobot_suture/NeedleInsertion-v0", obs_type="state", marks=True)

    env = gym.make("lerobot_suture/RunningSuture-v0", marks=True, **kwargs)
    obs, _ = env.reset(seed=0)
    base = env.unwrapped
    expert = ScriptedExpert()
    expert.reset(env)
    pairs = {tuple(np.round(obs[MARKS_KEY], 6))}
    while base.throw_index == 0:
        obs, _, terminated, truncated, _ = env.step(expert.act(base))
        np.testing.assert_allclose(
            obs[MARKS_KEY], np.concatenate([base.entry_point, base.exit_point]), atol=1e-6
        )
        pairs.add(tuple(np.round(obs[MARKS_KEY], 6)))
        assert not (terminated or truncated), "the first throw did not end"
    env.close()
    assert len(pairs) == 2  # the first throw's pair, then the second's


def test_a_recording_with_the_marks_stores_them_and_a_policy_that_reads_them_gets_them(tmp_path):
    from types import SimpleNamespace

    import gymnasium as gym
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_suture.datasets import metadata
    from lerobot_suture.datasets.features import ENV_STATE_KEY
    from lerobot_suture.datasets.record import record
    from lerobot_suture.datasets.record_config import RecordConfig
    from lerobot_suture.runtime.policy import env_kwargs_for_policy
    from lerobot_suture.sim.wound_marks import MARKS_NAMES

    root = tmp_path / "data"
    cfg = dict(repo_id="suture-tests/marks", root=str(root), image_size=32, num_episodes=1, val_fraction=0.0)
    record(RecordConfig(**cfg, marks=True))
    dataset = LeRobotDataset("suture-tests/marks", root=root)
    assert dataset.meta.features[ENV_STATE_KEY]["names"] == list(MARKS_NAMES)
    seed = metadata.read_episode_log(root)["episodes"][0]["seed"]
    env = gym.make("lerobot_suture/NeedleInsertion-v0", disable_env_checker=True, obs_type="state")
    env.reset(seed=seed)
    base = env.unwrapped
    np.testing.assert_allclose(
        dataset[0][ENV_STATE_KEY].numpy(), np.r_[base.entry_point, base.exit_point], atol=1e-6
    )
    env.close()
    assert "--marks=true" in RecordConfig(**cfg, marks=True).command()
    from lerobot_suture.datasets.card import render_description

    card = render_description(root)
    assert "wound marks (`observation.environment_state`)" in card and "needle centre, rotation" not in card
    with pytest.raises(ValueError, match="--marks=true"):
        record(RecordConfig(**{**cfg, "num_episodes": 2}, resume=True))
    with pytest.raises(ValueError, match="--obs_type=pixels_agent_pos"):
        RecordConfig(**cfg, obs_type="pixels_agent_pos_state", marks=True)

    image = PolicyFeature(type=FeatureType.VISUAL, shape=(3, 32, 32))
    features = {
        "observation.images.endoscope": image,
        "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(10,)),
        ENV_STATE_KEY: PolicyFeature(type=FeatureType.ENV, shape=(6,)),
    }
    kwargs = env_kwargs_for_policy(SimpleNamespace(input_features=features))
    assert kwargs == {"obs_type": "pixels_agent_pos", "image_size": 32, "marks": True}
    privileged = {**features, ENV_STATE_KEY: PolicyFeature(type=FeatureType.ENV, shape=(18,))}
    assert (
        env_kwargs_for_policy(SimpleNamespace(input_features=privileged))["obs_type"]
        == "pixels_agent_pos_state"
    )
