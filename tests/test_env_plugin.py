"""The LeRobot env plugin: discovered by name, built by lerobot's own factory, vectorized."""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import draccus
import numpy as np
import pytest
from lerobot.envs.configs import EnvConfig
from lerobot.envs.factory import make_env
from lerobot.envs.utils import check_env_attributes_and_types, env_to_policy_features, preprocess_observation
from lerobot.utils.import_utils import register_third_party_plugins

from lerobot_suture.sim.task import TASK


@pytest.fixture(scope="module")
def suture_config_cls():
    register_third_party_plugins()
    assert "suture" in EnvConfig.get_known_choices(), "lerobot did not discover lerobot_env_suture"
    return EnvConfig.get_choice_class("suture")


@dataclass
class EvalLike:  # how lerobot-eval and lerobot-train nest the env config
    env: EnvConfig


def _parse_env(*flags: str) -> EnvConfig:
    """The env config from ``--env.*`` flags, as LeRobot's commands parse it (plugins registered first)."""
    return draccus.parse(EvalLike, args=["--env.type=suture", *flags]).env


def test_policy_features_from_env_config(suture_config_cls):
    cfg = suture_config_cls(image_size=32)
    features = env_to_policy_features(cfg)
    assert features["observation.images.endoscope"].shape == (3, 32, 32)
    assert features["observation.state"].shape == (10,)
    assert features["action"].shape == (10,)
    state_cfg = suture_config_cls(obs_type="state")
    assert env_to_policy_features(state_cfg)["observation.environment_state"].shape == (18,)
    assert "observation.images.endoscope" not in env_to_policy_features(state_cfg)


def test_cli_flags_parse_nested_cbf_and_scenario(suture_config_cls):
    cfg = _parse_env("--env.scenario=needle_drop", "--env.cbf.enabled=true", "--env.cbf.alpha=3.0")
    assert isinstance(cfg, suture_config_cls)
    assert cfg.scenario == "needle_drop" and cfg.cbf.enabled and cfg.cbf.alpha == 3.0
    assert cfg.gym_kwargs["cbf"] is cfg.cbf
    assert suture_config_cls().gym_kwargs["cbf"] is None


@pytest.mark.parametrize(
    "flag, message",
    [
        ("--env.scenario=earthquake", "`scenario` must be one of ('nominal', "),
        ("--env.obs_type=pixels", "`obs_type` must be one of ('pixels_agent_pos', "),
        ("--env.fps=30", "`fps` must be 10 (the env's control rate). Got 30."),
        ("--env.episode_length=0", "`episode_length` must be >= 1. Got 0."),
        ("--env.image_size=8", "`image_size` must be in [16, 640] px. Got 8."),
        ("--env.render_size=1024", "`render_size` must be in [16, 640] px. Got 1024."),
        (
            "--env.appearance.noise=0.5",
            "`appearance.noise` must be in [0, 0.25] (fraction of full scale). Got 0.5.",
        ),
    ],
)
def test_bad_config_values_raise_naming_the_field(suture_config_cls, flag, message):
    """Each check of the env config, from the flag as lerobot-eval and lerobot-train parse it."""
    with pytest.raises(draccus.utils.ParsingError) as err:
        _parse_env(flag)
    assert isinstance(err.value.__cause__, ValueError) and message in str(err.value.__cause__)


def test_async_vector_env_through_lerobot_factory(suture_config_cls):
    cfg = suture_config_cls(image_size=32, render_size=32, episode_length=3)
    envs = make_env(cfg, n_envs=2, use_async_envs=True)
    vec = envs["suture"][0]
    try:
        assert vec.call("_max_episode_steps") == (3, 3)
        # lerobot-eval asks every worker for the task; a worker without it dies and takes the run with it.
        assert vec.call("task_description") == (TASK, TASK) and vec.get_attr("task") == (TASK, TASK)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            check_env_attributes_and_types(vec)
        obs, _ = vec.reset(seed=[0, 1])
        batch = preprocess_observation(obs)
        assert batch["observation.images.endoscope"].shape == (2, 3, 32, 32)
        assert batch["observation.state"].shape == (2, 10)
        action = obs["agent_pos"].astype(np.float32)  # hold the current pose
        for _ in range(3):
            obs, _, terminated, truncated, info = vec.step(action)
        assert truncated.all()
        assert "final_info" in info and "is_success" in info["final_info"]
        frames = vec.call("render")
        assert frames[0].shape == (32, 32, 3)
    finally:
        vec.close()


def test_cbf_enabled_from_the_env_config_wraps_every_env(suture_config_cls):
    cfg = suture_config_cls(obs_type="state", episode_length=2)
    cfg.cbf.enabled = True
    vec = make_env(cfg, n_envs=1, use_async_envs=False)["suture"][0]
    try:
        obs, info = vec.reset(seed=[0])
        assert "cbf_active" in info and "h" in info
        obs, _, _, _, info = vec.step(obs["agent_pos"].astype(np.float32))
        assert "v_safe" in info and not info["cbf_active"][0]  # the tip is far above the wound
    finally:
        vec.close()


def test_appearance_flags_reach_the_env(suture_config_cls):
    """``--env.appearance.<option>`` as lerobot-eval parses it; the default kwargs do not name it."""
    cfg = _parse_env("--env.obs_type=state", "--env.appearance.camera_roll=0.2")
    assert cfg.gym_kwargs["appearance"]["camera_roll"] == 0.2
    assert "appearance" not in suture_config_cls().gym_kwargs
    vec = make_env(cfg, n_envs=1, use_async_envs=False)["suture"][0]
    try:
        vec.reset(seed=[0])
        sample = vec.envs[0].unwrapped.appearance_sample
        assert sample is not None and 0 < abs(sample.camera_roll) <= 0.2
    finally:
        vec.close()


def test_the_wrist_camera_flag_adds_its_image(suture_config_cls):
    """``--env.wrist_camera=true``: ``observation.images.wrist`` beside the endoscope, through LeRobot's factory
    and preprocessing; the default kwargs do not name it, and a config without images refuses it."""
    cfg = _parse_env("--env.wrist_camera=true", "--env.image_size=32", "--env.episode_length=2")
    features = env_to_policy_features(cfg)
    assert features["observation.images.wrist"].shape == features["observation.images.endoscope"].shape
    assert "wrist_camera" not in suture_config_cls().gym_kwargs
    vec = make_env(cfg, n_envs=1, use_async_envs=False)["suture"][0]
    try:
        obs, _ = vec.reset(seed=[0])
        batch = preprocess_observation(obs)
        assert batch["observation.images.wrist"].shape == (1, 3, 32, 32)
    finally:
        vec.close()
    with pytest.raises(ValueError, match="--env.obs_type=pixels_agent_pos"):
        suture_config_cls(obs_type="state", wrist_camera=True)


def test_the_marks_flag_adds_the_wound_s_marks_as_environment_state(suture_config_cls):
    """``--env.marks=true``: the current throw's entry and exit marks as ``observation.environment_state``
    (6,), through LeRobot's factory and preprocessing; a config whose obs_type holds the privileged state refuses it."""
    cfg = _parse_env("--env.marks=true", "--env.image_size=32", "--env.episode_length=2")
    assert env_to_policy_features(cfg)["observation.environment_state"].shape == (6,)
    assert "marks" not in suture_config_cls().gym_kwargs
    vec = make_env(cfg, n_envs=1, use_async_envs=False)["suture"][0]
    try:
        obs, _ = vec.reset(seed=[0])
        batch = preprocess_observation(obs)
        base = vec.envs[0].unwrapped
        expected = np.concatenate([base.entry_point, base.exit_point])
        np.testing.assert_allclose(batch["observation.environment_state"][0].numpy(), expected, atol=1e-6)
    finally:
        vec.close()
    with pytest.raises(ValueError, match="--env.obs_type=pixels_agent_pos"):
        suture_config_cls(obs_type="pixels_agent_pos_state", marks=True)


def test_the_subtask_flag_adds_the_high_level_s_reading_after_the_marks(suture_config_cls):
    """``--env.subtask=true``: the high level's subtask and throw after the marks in
    ``observation.environment_state`` (11,), through LeRobot's factory and preprocessing."""
    cfg = _parse_env(
        "--env.marks=true", "--env.subtask=true", "--env.image_size=32", "--env.episode_length=2"
    )
    assert env_to_policy_features(cfg)["observation.environment_state"].shape == (11,)
    vec = make_env(cfg, n_envs=1, use_async_envs=False)["suture"][0]
    try:
        obs, _ = vec.reset(seed=[0])
        state = preprocess_observation(obs)["observation.environment_state"][0].numpy()
        np.testing.assert_array_equal(state[6:], [1, 0, 0, 0, 0])  # the insert of throw 0
    finally:
        vec.close()
    with pytest.raises(ValueError, match="--env.obs_type=pixels_agent_pos"):
        suture_config_cls(obs_type="state", subtask=True)


def test_the_arc_guard_flag_reaches_the_env_and_the_robot(suture_config_cls):
    """``--env.arc_guard=true`` through LeRobot's factory, ``--robot.arc_guard=true`` through the simulated arm's
    env; both off by default."""
    from lerobot_robot_suture.config_suture_sim import SutureSimConfig

    cfg = _parse_env("--env.arc_guard=true", "--env.image_size=32", "--env.episode_length=2")
    assert "arc_guard" not in suture_config_cls().gym_kwargs
    vec = make_env(cfg, n_envs=1, use_async_envs=False)["suture"][0]
    try:
        assert vec.envs[0].unwrapped.drive.needle_on_arc is True
    finally:
        vec.close()
    assert SutureSimConfig(arc_guard=True).env_kwargs()["arc_guard"] is True
    assert "arc_guard" not in SutureSimConfig().env_kwargs()
