"""The scripted pull (``sim.pull_servo``): from the jaw's measured pose at the hold it turns the needle out about its
centre, within the strain bound, on the real env; and the chain written with ``--scripted_pull=true`` extracts with
no learned action."""

from __future__ import annotations

import math

import numpy as np
import pytest
from lerobot.envs.utils import preprocess_observation
from lerobot_policy_suture_chain.assemble import ChainCommandConfig, write_chain
from test_regrasp_servo import SEED, _conditioned_act, _extraction_env, _regrasp

from lerobot_suture.runtime.policy import load_policy
from lerobot_suture.sim.extraction import STRAIN_BOUND
from lerobot_suture.sim.geometry import NEEDLE_RADIUS
from lerobot_suture.sim.pull_servo import PULL_ANGLE, PullServo, PullServoConfig, turned_jaw
from lerobot_suture.sim.regrasp_servo import RegraspServo
from lerobot_suture.sim.relative_actions import measured_jaw, relative_action
from lerobot_suture.sim.subtasks import JAW_INDEX


def test_the_pull_turns_the_held_jaw_about_the_needle_centre_through_its_angle():
    """A kinematic jaw: every target stays one needle radius from the centre the hold gives, on the plane normal
    the jaw's z axis gives, turns by the drive rate a step, and the turn ends at ``pull_angle``."""
    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    pose = np.concatenate([[0.01, -0.02, 0.03], q[:, 0], q[:, 1], [0.85]])
    servo = PullServo(pose)
    jaw_pos, jaw_rot = measured_jaw(pose)
    np.testing.assert_allclose(servo.centre, jaw_pos + NEEDLE_RADIUS * jaw_rot[:, 1])
    targets = []
    while not servo.done:
        targets.append(servo.act())
    cfg = servo.config
    assert len(targets) == math.ceil(PULL_ANGLE / (cfg.drive_rate * cfg.control_dt))
    for k, target in enumerate(targets):
        target_pos, target_rot = measured_jaw(target.astype(np.float64))
        assert target[JAW_INDEX] == 1.0
        assert abs(np.linalg.norm(target_pos - servo.centre) - NEEDLE_RADIUS) < 1e-6
        assert abs((target_pos - servo.centre) @ servo.axis) < 1e-6  # in the needle's plane
        np.testing.assert_allclose(target_rot[:, 2], jaw_rot[:, 2], atol=1e-6)  # about the jaw's own z axis
        angle = min(PULL_ANGLE, (k + 1) * cfg.drive_rate * cfg.control_dt)
        np.testing.assert_allclose(
            target_pos, turned_jaw(jaw_pos, jaw_rot, servo.centre, servo.axis, angle)[0]
        )
    # The pull's sense: the jaw first moves along its -x axis, the wire's tangent towards the tip: tip first.
    first = measured_jaw(targets[0].astype(np.float64))[0] - jaw_pos
    assert first @ jaw_rot[:, 0] < 0 < abs(first @ jaw_rot[:, 0]) - abs(first @ jaw_rot[:, 1])
    with pytest.raises(RuntimeError, match="next subtask"):
        servo.act()


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("drive_rate", 0.0, "drive_rate"),
        ("control_dt", float("nan"), "control_dt"),
        ("pull_angle", 0.0, "pull_angle"),
        ("pull_angle", 3.2, "pull_angle"),
        ("pull_angle", float("nan"), "pull_angle"),
    ],
)
def test_the_pull_config_refuses_what_it_cannot_run(field, value, match):
    with pytest.raises(ValueError, match=match):
        PullServoConfig(**{field: value})


@pytest.mark.parametrize("scenario", ["nominal", "phantom_moved_after_insertion"])
def test_regrasp_then_pull_on_what_the_robot_measures_extracts_within_the_strain_bound(scenario):
    """The servo takes the tip, the pull turns it out: the extraction succeeds, the tissue strained less than a
    tenth of its bound. Only the measured pose and the planned regrasp act; the env's verdict judges."""
    env = _extraction_env(image_size=32, scenario=scenario)
    try:
        observation, _ = env.reset(seed=SEED)
        servo, pull, info = RegraspServo(), None, {}
        for _ in range(env.spec.max_episode_steps):
            if servo.done and pull is None:
                assert servo.held
                pull = PullServo(observation["agent_pos"])
            action = (
                servo.act(observation["agent_pos"], _regrasp(observation)) if pull is None else pull.act()
            )
            observation, _, terminated, truncated, info = env.step(action)
            if terminated or truncated:
                break
        assert info["is_success"] and pull is not None and not pull.done  # out before the whole turn
        assert info["tissue_strain"] < 0.1 * STRAIN_BOUND
    finally:
        env.close()


def test_the_chain_scripts_the_regrasp_and_the_pull_and_extracts(tmp_path):
    """`lerobot-suture chain --scripted_regrasp=true --scripted_pull=true` on the real env: after the insert lets
    go, the servo and then the pull give every action (an untrained extract policy never acts) and the
    extraction succeeds; a chain config refuses the pull without the scripted regrasp."""
    policy = _conditioned_act(tmp_path / "policy")
    with pytest.raises(ValueError, match="scripted_regrasp=true"):
        write_chain(ChainCommandConfig(output_dir=tmp_path / "refused", policy=policy, scripted_pull=True))
    out = write_chain(
        ChainCommandConfig(
            output_dir=tmp_path / "chain", policy=policy, scripted_regrasp=True, scripted_pull=True
        )
    )
    chain, pre, post = load_policy(out)
    assert chain.config.scripted_pull
    env = _extraction_env()
    try:
        observation, _ = env.reset(seed=SEED)
        chain.reset()
        post(chain.select_action(pre(preprocess_observation(observation))))
        let_go = observation["agent_pos"].copy()
        let_go[JAW_INDEX] = 0.0  # the insert ends at the wound
        observation, *_ = env.step(let_go)
        pulled, info = 0, {}
        for _ in range(env.spec.max_episode_steps - 1):
            action = post(chain.select_action(pre(preprocess_observation(observation))))
            extract = chain.extracts[0]
            assert extract is not None and extract.regrasps == 1
            if extract.pull is not None:
                pulled += 1
                assert extract.servo.held
            observation, _, terminated, truncated, info = env.step(action[0].numpy())
            if terminated or truncated:
                break
        assert info["is_success"] and pulled > 20
    finally:
        env.close()


def test_the_scripted_extract_pulls_after_the_hold_hands_back_and_regrasps_a_needle_that_slipped():
    """A kinematic arm whose jaw stops on a wire: the regrasp servo acts until the hold, the pull from the next
    step to the end of its turn (``handed_back`` on its last action), then None (the policy acts); a jaw that
    then reads empty starts a new regrasp, which opens the jaw first."""
    from lerobot_suture.sim.scripted_extract import ScriptedExtract

    pose = np.array([0.01, -0.02, 0.03, 1, 0, 0, 0, 1, 0, 0.0])
    grasp = np.concatenate([pose[:3] + [0.002, -0.001, 0.004], [0, 1, 0, -1, 0, 0], [0.0]])
    extract, kinds = ScriptedExtract(pull=True), []
    for _ in range(400):
        target = relative_action(*measured_jaw(pose), grasp)[:9]
        action = extract.act(pose, target)
        if action is None:
            break
        kinds.append("pull" if extract.pulling or extract.handed_back else "regrasp")
        pose = np.concatenate([action[:9], [0.85 if action[9] > 0.5 else 0.0]])  # the wire stops the jaw
    assert action is None and extract.servo.held and extract.pull.done and extract.regrasps == 1
    assert extract.closings == 1
    first_pull = kinds.index("pull")
    assert set(kinds[first_pull:]) == {"pull"}
    assert len(kinds) - first_pull == math.ceil(PULL_ANGLE / (0.6 * 0.1))
    slipped = pose.copy()
    slipped[JAW_INDEX] = 1.0
    action = extract.act(slipped, relative_action(*measured_jaw(slipped), grasp)[:9])
    assert extract.regrasps == 2 and extract.pull is None and action[JAW_INDEX] == 0.0
    assert extract.closings == 1  # the first servo's closing, counted across the regrasp
