"""EnvHub: `envs/hub/` as a Hub repository, loaded by LeRobot's own `make_env("user/repo")`.

The Hub is offline (conftest); the repository is put in a local Hugging Face cache exactly where
`hf_hub_download` looks for it, so LeRobot's download, import and call path all run for real.
"""

from __future__ import annotations

import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from lerobot.envs.configs import HubEnvConfig
from lerobot.envs.factory import make_env
from lerobot.envs.utils import _import_hub_module

from lerobot_suture.sim.task import TASK

HUB_FOLDER = Path(__file__).resolve().parents[1] / "envs" / "hub"
REPO_ID = "someuser/suture"
COMMIT = "0123456789abcdef0123456789abcdef01234567"


@pytest.fixture(scope="module")
def hub_cache(tmp_path_factory) -> Path:
    """A Hugging Face cache holding `envs/hub/` as the `main` revision of model repo `someuser/suture`."""
    cache = tmp_path_factory.mktemp("hf_cache")
    repo = cache / f"models--{REPO_ID.replace('/', '--')}"
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text(COMMIT)
    shutil.copytree(HUB_FOLDER, repo / "snapshots" / COMMIT, ignore=shutil.ignore_patterns("__pycache__"))
    return cache


@dataclass
class SmallSutureHubEnv(HubEnvConfig):
    """A config as a user would pass to `make_env`: the Hub path and gym kwargs for the env."""

    hub_path: str | None = REPO_ID
    image_size: int = 32
    episode_length: int = 3

    @property
    def gym_kwargs(self) -> dict:
        return {"image_size": self.image_size, "render_size": 32, "max_episode_steps": self.episode_length}


def test_hub_env_async_through_lerobot_make_env(hub_cache):
    envs = make_env(
        REPO_ID, n_envs=2, use_async_envs=True, hub_cache_dir=str(hub_cache), trust_remote_code=True
    )
    vec = envs["suture"][0]
    try:
        assert isinstance(vec, gym.vector.AsyncVectorEnv)
        assert vec.call("_max_episode_steps") == (100, 100)
        assert vec.call("task_description") == (TASK, TASK)
        obs, _ = vec.reset(seed=[0, 1])
        assert obs["pixels"]["endoscope"].shape == (2, 96, 96, 3)
        assert obs["pixels"]["endoscope"].dtype == np.uint8
        assert obs["agent_pos"].shape == (2, 10)
        action = obs["agent_pos"].astype(np.float32)  # hold the current pose
        obs, reward, terminated, truncated, info = vec.step(action)
        assert reward.shape == terminated.shape == truncated.shape == (2,)
        assert obs["agent_pos"].shape == (2, 10)
    finally:
        vec.close()


def test_hub_env_honours_the_config_gym_kwargs(hub_cache):
    envs = make_env(SmallSutureHubEnv(), n_envs=2, hub_cache_dir=str(hub_cache), trust_remote_code=True)
    vec = envs["suture"][0]
    try:
        assert vec.call("_max_episode_steps") == (3, 3)
        obs, _ = vec.reset(seed=[0, 1])
        assert obs["pixels"]["endoscope"].shape == (2, 32, 32, 3)
        action = obs["agent_pos"].astype(np.float32)
        for _ in range(3):
            obs, _, terminated, truncated, info = vec.step(action)
        assert truncated.all()
        assert "final_info" in info and "is_success" in info["final_info"]  # SAME_STEP autoreset
        assert vec.call("render")[0].shape == (32, 32, 3)
    finally:
        vec.close()


def test_hub_env_defaults_are_the_suture_env_type_defaults():
    from lerobot_env_suture.configuration_suture import SutureEnvConfig

    module = _import_hub_module(str(HUB_FOLDER / "env.py"), REPO_ID)
    assert module.DEFAULT_GYM_KWARGS == SutureEnvConfig().gym_kwargs


def test_hub_env_without_lerobot_suture_says_what_to_install(hub_cache, monkeypatch):
    monkeypatch.setitem(sys.modules, "lerobot_suture", None)  # as if not installed
    with pytest.raises(ModuleNotFoundError, match="pip install lerobot_suture"):
        make_env(REPO_ID, hub_cache_dir=str(hub_cache), trust_remote_code=True)


def test_hub_env_rejects_bad_n_envs(hub_cache):
    with pytest.raises(ValueError, match="`n_envs` must be an integer >= 1. Got 0"):
        make_env(REPO_ID, n_envs=0, hub_cache_dir=str(hub_cache), trust_remote_code=True)
