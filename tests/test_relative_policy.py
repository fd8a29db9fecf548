"""A policy trained on relative actions carries that in its checkpoint and hands out absolute targets: LeRobot's
`make_policy` marks it from the dataset, its saved processors compose each action with the measured jaw pose,
and its enforced gate's hold keeps the arm where it is."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from lerobot_suture.sim.geometry import matrix_from_rot6
from lerobot_suture.sim.relative_actions import MAX_RELATIVE_STEP, RELATIVE_ACTION_NAMES, relative_action
from lerobot_suture.sim.tasks import TASKS


def save_relative_policy(root, directory, task: str, **recorded):
    """An untrained tiny ensemble built by LeRobot's `make_policy` from a one-episode ``task`` dataset recorded
    at ``root`` with relative actions (``recorded``: further `RecordConfig` options), saved at ``directory`` as
    `lerobot-train` saves one; returns ``directory``."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy, make_pre_post_processors
    from lerobot_policy_ensemble_diffusion import EnsembleDiffusionConfig
    from policy_builders import TINY_POLICY_KWARGS

    from lerobot_suture.datasets.record import record
    from lerobot_suture.datasets.record_config import RecordConfig

    repo_id = f"suture-tests/relative-{task}"
    record(
        RecordConfig(
            repo_id=repo_id,
            root=str(root),
            task=task,
            num_episodes=1,
            val_fraction=0.0,
            relative_actions=True,
            **recorded,
        )
    )
    meta = LeRobotDatasetMetadata(repo_id, root=root)
    torch.manual_seed(0)
    policy = make_policy(EnsembleDiffusionConfig(**TINY_POLICY_KWARGS, device="cpu"), ds_meta=meta)
    policy.save_pretrained(directory)
    for pipeline in make_pre_post_processors(policy.config, dataset_stats=meta.stats):
        pipeline.save_pretrained(directory)
    return directory


def check_targets_one_step_from_the_jaw(runner, env, steps: int = 6) -> None:
    """``runner`` drives ``env`` from the scene of seed 5; every target it hands out lies within one relative
    step of the jaw. Read as an absolute pose, a raw relative output would sit near the base frame's origin."""
    observation, _ = env.reset(seed=5)
    runner.reset()
    for _ in range(steps):
        target = runner.act(observation)
        jaw_pos, jaw_rot = env.unwrapped.jaw_pose()
        motion = relative_action(jaw_pos, jaw_rot, target)
        assert np.all(np.abs(motion[:3]) <= MAX_RELATIVE_STEP + 1e-5), motion[:3]
        observation, *_ = env.step(target)


@pytest.fixture(scope="module")
def relative_policy_dir(tmp_path_factory):
    """The tiny relative-action ensemble of a one-episode extraction dataset (endoscope and state)."""
    root = tmp_path_factory.mktemp("relative_data") / "data"
    return save_relative_policy(
        root, tmp_path_factory.mktemp("relative_policy") / "pretrained_model", "extraction"
    )


def test_the_checkpoint_says_it_was_trained_on_relative_actions(relative_policy_dir, tiny_policy_dir):
    config = json.loads((relative_policy_dir / "config.json").read_text())
    assert config["action_feature_names"] == list(RELATIVE_ACTION_NAMES)
    steps = json.loads((relative_policy_dir / "policy_postprocessor.json").read_text())["steps"]
    assert steps[-1]["registry_name"] == "jaw_frame_absolute_actions"
    absolute = json.loads((tiny_policy_dir / "policy_postprocessor.json").read_text())["steps"]
    assert "jaw_frame_absolute_actions" not in [s.get("registry_name") for s in absolute]


def test_a_relative_policy_hands_the_plain_env_targets_one_step_from_the_jaw(relative_policy_dir):
    import gymnasium as gym

    from lerobot_suture.runtime.policy import GateMode, PolicyRunner

    runner = PolicyRunner.from_pretrained(relative_policy_dir, GateMode.REPORT)
    check_targets_one_step_from_the_jaw(
        runner, gym.make(TASKS["extraction"].gym_id, obs_type="pixels_agent_pos")
    )


def test_the_released_gate_of_a_relative_policy_holds_the_measured_pose(relative_policy_dir):
    import gymnasium as gym

    from lerobot_suture.runtime.policy import GateMode, PolicyRunner

    runner = PolicyRunner.from_pretrained(relative_policy_dir, GateMode.REPORT)
    env = gym.make(TASKS["extraction"].gym_id, obs_type="pixels_agent_pos")
    observations = [env.reset(seed=seed)[0] for seed in (1, 2)]
    batch = runner.preprocess(observations)
    held = runner.postprocessor(runner.policy._hold_action(batch)).numpy()
    measured = np.stack([o["agent_pos"] for o in observations])
    np.testing.assert_allclose(held[:, :3], measured[:, :3], atol=1e-6)
    for h, m in zip(held, measured, strict=True):
        np.testing.assert_allclose(matrix_from_rot6(h[3:9]), matrix_from_rot6(m[3:9]), atol=1e-5)
    np.testing.assert_allclose(held[:, 9], measured[:, 9], atol=1e-5)


def test_the_post_processor_names_what_it_lacks(relative_policy_dir):
    import gymnasium as gym
    from lerobot.processor import PolicyProcessorPipeline
    from lerobot.processor.converters import policy_action_to_transition, transition_to_policy_action

    from lerobot_suture.runtime.policy import GateMode, PolicyRunner

    alone = PolicyProcessorPipeline.from_pretrained(
        relative_policy_dir,
        config_filename="policy_postprocessor.json",
        to_transition=policy_action_to_transition,
        to_output=transition_to_policy_action,
    )  # loaded without its pre-processor: nothing pairs them
    with pytest.raises(RuntimeError, match="run its pre-processor"):
        alone(torch.zeros(1, 10))
    runner = PolicyRunner.from_pretrained(relative_policy_dir, GateMode.REPORT)
    runner.preprocess([gym.make(TASKS["extraction"].gym_id, obs_type="pixels_agent_pos").reset(seed=0)[0]])
    with pytest.raises(ValueError, match="one per step"):
        runner.postprocessor(torch.zeros(1, 4, 10))  # a whole chunk


def test_lerobot_rollout_runs_a_relative_policy_on_the_arm(relative_policy_dir, tmp_path):
    from robot_commands import base_rollout

    steps = base_rollout(
        relative_policy_dir, tmp_path / "trace.jsonl", "--robot.seed=5", "--robot.task=extraction"
    )
    assert len(steps) >= 5
    for before, after in zip(steps, steps[1:], strict=False):
        pose = np.asarray(before["pose"])
        motion = relative_action(pose[:3], matrix_from_rot6(pose[3:9]), np.asarray(after["action"]))
        assert np.all(np.abs(motion[:3]) <= MAX_RELATIVE_STEP + 1e-4), motion[:3]


def test_the_env_wrapper_and_the_post_processor_compose_from_the_same_measured_pose():
    """A recorded label and a trained policy's action meet the same pose: the last observation's ``agent_pos``
    (the endoscope's rendering refreshes MuJoCo's kinematics after it is read, so the simulator's pose of the
    moment is not the one the robot reported)."""
    import gymnasium as gym
    from lerobot_policy_ensemble_diffusion.jaw_frame_actions import targets_from_relative

    from lerobot_suture.sim.relative_actions import find_relative_actions

    env = gym.make(TASKS["extraction"].gym_id, relative_actions=True)
    observation, _ = env.reset(seed=3)
    rng = np.random.default_rng(0)
    for _ in range(4):
        motion = np.concatenate([rng.uniform(-0.004, 0.004, 3), [1, 0.02, 0, -0.02, 1, 0], [0.5]])
        expected = targets_from_relative(observation["agent_pos"][None], motion[None])[0]
        np.testing.assert_allclose(find_relative_actions(env).action(motion), expected, atol=1e-12)
        observation, *_ = env.step(motion.astype(np.float32))


@pytest.mark.slow
def test_a_chain_around_a_relative_policy_hands_the_env_targets_one_step_from_the_jaw(tmp_path):
    """A subtask-conditioned policy trained on relative actions, inside a ``suture_chain``: the chain runs the
    policy's own processor pair on each step, so the running suture's env gets absolute targets near the jaw."""
    import gymnasium as gym
    from lerobot_policy_suture_chain.assemble import ChainCommandConfig, write_chain

    from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy

    member = save_relative_policy(
        tmp_path / "data", tmp_path / "conditioned", "running_suture", marks=True, subtask=True
    )
    chain = write_chain(ChainCommandConfig(output_dir=tmp_path / "chain", policy=member))
    runner = PolicyRunner.from_pretrained(chain, GateMode.REPORT)
    env = gym.make(TASKS["running_suture"].gym_id, **env_kwargs_for_policy(runner.policy.config))
    check_targets_one_step_from_the_jaw(runner, env)
