"""The scripted regrasp (``sim.regrasp_servo``): it takes the needle's tip from the measured pose and the planned
regrasp alone, reaches again after a closing on nothing, and serves the chain's extract until the jaw holds the
tip, the extract policy pulling from there."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.utils import preprocess_observation
from lerobot.utils.constants import OBS_ENV_STATE
from lerobot_policy_suture_chain.assemble import ChainCommandConfig, write_chain
from lerobot_policy_suture_chain.configuration_suture_chain import SutureChainConfig
from policy_builders import SUTURE_INPUT_FEATURES, expert_dataset_stats, tiny_act_config

from lerobot_suture.runtime.policy import env_kwargs_for_policy, load_policy
from lerobot_suture.sim.regrasp_servo import RegraspServo, RegraspServoConfig, grasp_from_target
from lerobot_suture.sim.regrasp_target import REGRASP_TARGET_DIM
from lerobot_suture.sim.relative_actions import measured_jaw, relative_action
from lerobot_suture.sim.subtasks import JAW_INDEX, SUBTASK_DIM, subtask_vector
from lerobot_suture.sim.tasks import TASKS
from lerobot_suture.sim.wound_marks import MARKS_DIM

EXTRACTION_ID = TASKS["extraction"].gym_id
SEED = 27_000_003  # a nominal test seed of the extraction cell


def _extraction_env(**kwargs) -> gym.Env:
    return gym.make(EXTRACTION_ID, obs_type="pixels_agent_pos", marks=True, regrasp_target=True, **kwargs)


def _regrasp(observation: dict) -> np.ndarray:
    return observation["environment_state"][MARKS_DIM : MARKS_DIM + REGRASP_TARGET_DIM]


@pytest.mark.parametrize("source", ["marks", "release"])
def test_the_servo_takes_the_tip_from_what_the_robot_measures(source):
    """Driven on the measured pose and the planned regrasp alone, the jaw closes once and holds the needle's wire
    (the simulator's contact flag, read here only to judge it)."""
    env = _extraction_env(regrasp_from=source, image_size=32)
    try:
        for seed in (SEED, SEED + 1):
            observation, _ = env.reset(seed=seed)
            servo = RegraspServo()
            for _ in range(120):
                action = servo.act(observation["agent_pos"], _regrasp(observation))
                observation, _, terminated, truncated, _ = env.step(action)
                if servo.done or terminated or truncated:
                    break
            assert servo.done and servo.held and servo.closings == 1
            assert env.unwrapped.needle_grasped
            assert 0.5 < observation["agent_pos"][JAW_INDEX] < 0.95  # the wire stops the jaw short of closed
            with pytest.raises(RuntimeError, match="extract policy"):
                servo.act(observation["agent_pos"], _regrasp(observation))
    finally:
        env.close()


def test_a_closing_on_nothing_opens_and_reaches_again_up_to_its_attempts():
    """A kinematic arm that goes where it is told, with a jaw that closes fully (nothing between its faces): the
    servo judges each closing, reaches again, and hands over after ``attempts`` closings."""
    rng = np.random.default_rng(0)
    pose = np.array([0.01, -0.02, 0.03, 1, 0, 0, 0, 1, 0, 0.87])
    grasp = np.concatenate([pose[:3] + rng.normal(0, 0.004, 3), [0, 1, 0, -1, 0, 0], [0.0]])
    servo = RegraspServo(RegraspServoConfig(attempts=2))
    phases = []
    for _ in range(400):
        target = relative_action(*measured_jaw(pose), grasp)[:REGRASP_TARGET_DIM]
        action = servo.act(pose, target)
        phases.append(servo.phase)
        pose = np.concatenate([action[:9], [min(1.0, pose[JAW_INDEX] + 0.5) if action[9] > 0.5 else 0.0]])
        if servo.done:
            break
    assert servo.done and not servo.held and servo.closings == 2
    first_close = phases.index("close")
    again = phases[first_close:]
    assert "back_off" in again and "advance" in again  # the miss: back off, advance onto the grasp again
    deeper = measured_jaw(grasp)[1].T @ (
        pose[:3] - grasp[:3]
    )  # the second closing, 1 mm further along the jaw
    np.testing.assert_allclose(deeper, [0.0, 0.0, 0.001], atol=5e-4)
    np.testing.assert_allclose(
        grasp_from_target(pose, relative_action(*measured_jaw(pose), grasp)[:9])[0], grasp[:3]
    )


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("approach_speed", 0.0, "approach_speed"),
        ("turn_rate", float("nan"), "turn_rate"),
        ("settle_steps", -1, "settle_steps"),
        ("attempts", 0, "attempts"),
        ("holding_below", 0.4, "closed_above < holding_below"),
        ("search_depth", 0.003, "search_depth"),
        ("attempts", 7, "inside the jaw"),
    ],
)
def test_the_servo_config_refuses_what_it_cannot_run(field, value, match):
    with pytest.raises(ValueError, match=match):
        RegraspServoConfig(**{field: value})


def _conditioned_act(directory) -> str:
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    features = {
        **SUTURE_INPUT_FEATURES,
        OBS_ENV_STATE: PolicyFeature(type=FeatureType.ENV, shape=(MARKS_DIM + SUBTASK_DIM,)),
    }
    config = tiny_act_config(features)
    torch.manual_seed(0)
    ACTPolicy(config).save_pretrained(directory)
    for pipeline in make_pre_post_processors(config, dataset_stats=expert_dataset_stats(n_seeds=2)):
        pipeline.save_pretrained(directory)
    return directory


def test_the_chain_scripts_the_regrasp_then_its_extract_policy_pulls(tmp_path):
    """`lerobot-suture chain --scripted_regrasp=true`: the chain asks the env for the planned regrasp; once the
    jaw lets go at the wound (the extract begins), the servo acts until the jaw holds the tip, on the real env;
    then the extract policy, reset, acts; a jaw that then reads empty gets a new servo."""
    policy = _conditioned_act(tmp_path / "policy")
    out = write_chain(ChainCommandConfig(output_dir=tmp_path / "chain", policy=policy, scripted_regrasp=True))
    chain, pre, post = load_policy(out)
    assert chain.config.scripted_regrasp
    assert chain.config.input_features[OBS_ENV_STATE].shape == (MARKS_DIM + REGRASP_TARGET_DIM,)
    kwargs = env_kwargs_for_policy(chain.config)
    assert kwargs.get("marks") is True and kwargs.get("regrasp_target") is True
    env = _extraction_env()
    try:
        observation, _ = env.reset(seed=SEED)
        chain.reset()
        post(chain.select_action(pre(preprocess_observation(observation))))
        assert chain.readings == [("insert", 0)]
        let_go = observation["agent_pos"].copy()
        let_go[JAW_INDEX] = 0.0  # the surgeon's hand opens the jaw: the insert ends at the wound
        observation, *_ = env.step(let_go)
        servo_steps = 0
        for _ in range(120):
            action = post(chain.select_action(pre(preprocess_observation(observation))))
            assert chain.readings[0][0] == "extract"
            servo = chain.extracts[0].servo
            servo_steps += 1
            observation, *_ = env.step(action[0].numpy())
            if servo.done:
                break
        assert servo.done and env.unwrapped.needle_grasped and servo_steps > 20
        action = post(chain.select_action(pre(preprocess_observation(observation))))
        assert chain.extracts[0].servo is servo  # done: the extract policy acts, no new servo
        ref, ref_pre, ref_post = load_policy(out / "policies" / "all")
        ref.reset()
        batch = preprocess_observation(observation)
        extract = torch.from_numpy(subtask_vector("extract", 0))[None]
        batch[OBS_ENV_STATE] = torch.cat([batch[OBS_ENV_STATE][:, :MARKS_DIM], extract], dim=-1)
        assert torch.allclose(action, ref_post(ref.select_action(ref_pre(batch))), atol=1e-5)

        lost = {**observation, "agent_pos": observation["agent_pos"].copy()}
        lost["agent_pos"][JAW_INDEX] = 1.0  # the encoder reads the jaw empty: the needle slipped out
        action = post(chain.select_action(pre(preprocess_observation(lost))))
        assert chain.readings[0][0] == "extract" and chain.extracts[0].servo is not servo
        assert action[0, JAW_INDEX] == 0.0  # a new regrasp: it lets go first
    finally:
        env.close()


def test_a_chain_config_with_the_scripted_regrasp_needs_the_planned_regrasp():
    from lerobot.utils.constants import ACTION, OBS_STATE

    with pytest.raises(ValueError, match="--scripted_regrasp=true"):
        SutureChainConfig(
            subtask_policies=dict.fromkeys(("insert", "extract", "lay_down", "pick_up"), "all"),
            scripted_regrasp=True,
            input_features={
                OBS_STATE: PolicyFeature(FeatureType.STATE, (10,)),
                OBS_ENV_STATE: PolicyFeature(FeatureType.ENV, (MARKS_DIM,)),
            },
            output_features={ACTION: PolicyFeature(FeatureType.ACTION, (10,))},
        ).validate_features()
