"""The `running_suture` task: four pairs along the wound, a throw at a time, each scored as an insertion, the
episode's end on a throw off the marks or after the fourth, and the CBF guarding each throw."""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from lerobot_suture.expert import ScriptedExpert, iter_expert_steps
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.sim.running_suture import N_THROWS, PAIR_SPACING, pair_points
from lerobot_suture.sim.suture_env import SutureEnv
from lerobot_suture.sim.tasks import TASKS

RUNNING_ID = TASKS["running_suture"].gym_id


def test_four_pairs_cross_the_wound_along_it():
    pairs = [pair_points(k) for k in range(N_THROWS)]
    for entry, exit_ in pairs:
        assert entry[0] < 0 < exit_[0] and entry[1] == exit_[1] and np.linalg.norm(exit_ - entry) == 0.016
    ys = [entry[1] for entry, _ in pairs]
    np.testing.assert_allclose(np.diff(ys), PAIR_SPACING)
    assert abs(np.mean(ys)) < 1e-12
    env = SutureEnv(task="running_suture", obs_type="state")
    markers = [env.model.geom(f"entry_marker_{k}").pos for k in range(1, N_THROWS)]
    np.testing.assert_allclose([m[1] for m in markers], ys[1:])
    assert env.model.geom("entry_marker").pos[1] == ys[0]


def test_the_expert_runs_all_four_throws_each_on_the_marks():
    env = gym.make(RUNNING_ID, obs_type="state", cbf=CBFConfig(enabled=True), disable_env_checker=True)
    obs, info = env.reset(seed=0)
    assert info["throw_index"] == 0 and info["throws_on_marks"] == 0
    filtered = set()
    for step in iter_expert_steps(env, ScriptedExpert(), obs):
        if step.info["cbf_active"]:
            filtered.add(step.info["throw_index"])
    info = step.info
    assert step.terminated and info["is_success"] and info["throws_on_marks"] == N_THROWS
    assert [r["throw"] for r in info["throw_results"]] == list(range(N_THROWS))
    assert all(r["entry_error_m"] < 0.002 and r["exit_error_m"] < 0.002 for r in info["throw_results"])
    assert info["throws_extracted"] == N_THROWS - 1  # the last throw ends the suture
    assert filtered == set(range(N_THROWS))  # the CBF guarded every throw
    steps = [r["over_step"] for r in info["throw_results"]]
    assert steps == sorted(steps) and steps[-1] < TASKS["running_suture"].max_episode_steps


def test_a_throw_off_the_marks_ends_the_suture_as_a_failure():
    env = gym.make(RUNNING_ID, obs_type="state", disable_env_checker=True)
    obs, _ = env.reset(seed=1)
    u = env.unwrapped
    u._entry_local = u._entry_local + np.array([0.0, 0.004, 0.0])  # the expert aims 4 mm off the marked entry
    u._exit_local = u._exit_local + np.array([0.0, 0.004, 0.0])
    steps = list(iter_expert_steps(env, ScriptedExpert(), obs))
    info = steps[-1].info
    assert steps[-1].terminated and not info["is_success"]
    assert info["throws_on_marks"] == 0 and len(info["throw_results"]) == 1
    assert info["throw_results"][0]["entry_error_m"] > 0.002
