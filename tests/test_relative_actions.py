"""Actions relative to the jaw's measured pose: exact inversion, the same episodes as absolute actions, bad input
named, the recorded dataset and its card."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import lerobot_suture  # noqa: F401
from lerobot_suture.expert import ScriptedExpert, iter_expert_steps
from lerobot_suture.sim.geometry import matrix_from_rotvec, pose_vector
from lerobot_suture.sim.relative_actions import (
    MAX_RELATIVE_STEP,
    RELATIVE_ACTION_NAMES,
    RelativeActions,
    absolute_action,
    env_action,
    find_relative_actions,
    relative_action,
)
from lerobot_suture.sim.tasks import TASKS

_vector = st.lists(st.floats(-1.0, 1.0, allow_nan=False), min_size=3, max_size=3).map(np.array)


@settings(max_examples=200, deadline=None)
@given(_vector, _vector, _vector, _vector, st.floats(0.0, 1.0))
def test_a_relative_action_composes_back_to_its_absolute_target(
    jaw_pos, jaw_turn, target_pos, target_turn, jaw
):
    jaw_rot = matrix_from_rotvec(3.0 * jaw_turn)
    target = pose_vector(0.05 * target_pos, matrix_from_rotvec(3.0 * target_turn), jaw)
    relative = relative_action(0.05 * jaw_pos, jaw_rot, target)
    np.testing.assert_allclose(absolute_action(0.05 * jaw_pos, jaw_rot, relative), target, atol=1e-9)


def test_the_identity_is_a_hold():
    jaw_rot = matrix_from_rotvec(np.array([0.3, -0.2, 1.0]))
    jaw_pos = np.array([0.01, -0.02, 0.03])
    hold = relative_action(jaw_pos, jaw_rot, pose_vector(jaw_pos, jaw_rot, 1.0))
    np.testing.assert_allclose(hold, [0, 0, 0, 1, 0, 0, 0, 1, 0, 1], atol=1e-12)


def _expert_episode(task: str, seed: int, relative: bool) -> tuple[bool, np.ndarray, np.ndarray]:
    env = gym.make(TASKS[task].gym_id, obs_type="state", relative_actions=relative)
    obs, _ = env.reset(seed=seed)
    tips, actions = [], []
    for step in iter_expert_steps(env, ScriptedExpert(task=task), obs):
        tips.append(step.info["needle_tip_pos"])
        actions.append(step.action)
    env.close()
    return bool(step.info["is_success"]), np.array(tips), np.array(actions)


@pytest.mark.parametrize("task", ["insertion", "extraction"])
def test_the_expert_drives_the_same_episode_through_relative_actions(task):
    success, tips, _ = _expert_episode(task, 3, relative=False)
    success_rel, tips_rel, actions_rel = _expert_episode(task, 3, relative=True)
    assert success and success_rel
    assert tips.shape == tips_rel.shape
    np.testing.assert_allclose(tips_rel, tips, atol=1e-6)  # float32 actions: well under a micrometre
    assert np.abs(actions_rel[:, :3]).max() < MAX_RELATIVE_STEP  # nothing the wrapper clips


def test_bad_relative_actions_are_named_and_large_ones_clipped():
    env = gym.make(TASKS["insertion"].gym_id, obs_type="state", relative_actions=True)
    env.reset(seed=0)
    assert isinstance(find_relative_actions(env), RelativeActions)
    with pytest.raises(ValueError, match=r"shape \(10,\)"):
        env.step(np.zeros(9, dtype=np.float32))
    with pytest.raises(ValueError, match="NaN or inf at indices"):
        env.step(np.full(10, np.nan, dtype=np.float32))
    with pytest.raises(ValueError, match="rotation column"):
        env.step(np.zeros(10, dtype=np.float32))
    before, _ = env.unwrapped.jaw_pose()
    huge = np.array([1.0, 1.0, 1.0, 1, 0, 0, 0, 1, 0, 1], dtype=np.float32)
    env.step(huge)  # a metre asked for: clipped to MAX_RELATIVE_STEP, then the arm's speed limit
    after, _ = env.unwrapped.jaw_pose()
    assert np.linalg.norm(after - before) < 2 * np.sqrt(3) * MAX_RELATIVE_STEP
    plain = gym.make(TASKS["insertion"].gym_id, obs_type="state")
    plain.reset(seed=0)
    assert find_relative_actions(plain) is None
    np.testing.assert_array_equal(env_action(plain, np.arange(10.0)), np.arange(10.0, dtype=np.float32))


def test_a_dataset_recorded_with_relative_actions_says_so(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_suture.datasets.card import render_description
    from lerobot_suture.datasets.record import record
    from lerobot_suture.datasets.record_config import RecordConfig

    root = tmp_path / "data"
    cfg = dict(
        repo_id="suture-tests/relative",
        root=str(root),
        task="extraction",
        obs_type="state",
        num_episodes=1,
        val_fraction=0.0,
    )
    record(RecordConfig(**cfg, relative_actions=True))
    dataset = LeRobotDataset("suture-tests/relative", root=root)
    assert dataset.meta.features["action"]["names"] == list(RELATIVE_ACTION_NAMES)
    _, _, actions = _expert_episode("extraction", 0, relative=True)  # the recording's first seed
    np.testing.assert_allclose(dataset[0]["action"].numpy(), actions[0], atol=1e-7)
    assert "--relative_actions=true" in RecordConfig(**cfg, relative_actions=True).command()
    assert "composes its actions with the measured pose" in " ".join(render_description(root).split())
    with pytest.raises(ValueError, match="--relative_actions=true"):
        record(RecordConfig(**{**cfg, "num_episodes": 2}, resume=True))
