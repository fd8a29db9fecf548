"""The `suture_chain` policy type: the running suture's high level above one LeRobot policy per subtask, written
by `lerobot-suture chain` and loaded as LeRobot loads any policy."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.utils.constants import OBS_ENV_STATE, OBS_STATE
from lerobot_policy_suture_chain.assemble import ChainCommandConfig, main, write_chain
from lerobot_policy_suture_chain.configuration_suture_chain import SutureChainConfig
from lerobot_policy_suture_chain.modeling_suture_chain import environment_state_for
from policy_builders import (
    IMAGE_KEY,
    SUTURE_INPUT_FEATURES,
    expert_dataset_stats,
    tiny_act_config,
)

from lerobot_suture.runtime.policy import env_kwargs_for_policy, load_policy
from lerobot_suture.sim.regrasp_target import REGRASP_TARGET_DIM
from lerobot_suture.sim.subtasks import SUBTASK_DIM, subtask_vector
from lerobot_suture.sim.wound_marks import MARKS_DIM

HELD = 0.87
"""The jaw's closure on the needle's wire (an empty jaw closes to 1)."""
CONDITIONED_FEATURES = {
    **SUTURE_INPUT_FEATURES,
    OBS_ENV_STATE: PolicyFeature(type=FeatureType.ENV, shape=(MARKS_DIM + SUBTASK_DIM,)),
}


def _save_act(directory: Path, seed: int, input_features: dict | None = None) -> Path:
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    config = tiny_act_config(input_features)
    torch.manual_seed(seed)
    ACTPolicy(config).save_pretrained(directory)
    for pipeline in make_pre_post_processors(config, dataset_stats=expert_dataset_stats(n_seeds=2)):
        pipeline.save_pretrained(directory)
    return directory


@pytest.fixture(scope="module")
def subtask_policies(tmp_path_factory) -> tuple[Path, Path]:
    """A subtask-conditioned tiny ACT (it reads the marks, the subtask and the throw) and a plain one."""
    root = tmp_path_factory.mktemp("subtask_policies")
    return _save_act(root / "conditioned", 0, CONDITIONED_FEATURES), _save_act(root / "plain", 1)


def _batch(jaw: list[float], entry: np.ndarray, rng: np.random.Generator) -> dict:
    poses = np.tile(np.array([0.0, 0.0, 0.01, 1, 0, 0, 0, 1, 0, 0.0], dtype=np.float32), (len(jaw), 1))
    poses[:, :3] = entry  # at the entry mark, where a release ends an insert
    poses[:, 9] = jaw
    marks = np.tile(np.concatenate([entry, entry + [0.016, 0, 0]]).astype(np.float32), (len(jaw), 1))
    return {
        OBS_STATE: torch.from_numpy(poses),
        OBS_ENV_STATE: torch.from_numpy(marks),
        IMAGE_KEY: torch.from_numpy(rng.random((len(jaw), 3, 96, 96), dtype=np.float32)),
    }


def test_the_config_names_a_policy_for_every_subtask_and_nothing_else():
    with pytest.raises(ValueError, match=r"Missing \['extract', 'lay_down', 'pick_up'\]"):
        SutureChainConfig(subtask_policies={"insert": "all"}, device="cpu")
    with pytest.raises(ValueError, match="unknown \\['throw'\\]"):
        SutureChainConfig(
            subtask_policies=dict.fromkeys(("insert", "extract", "lay_down", "pick_up", "throw"), "all"),
            device="cpu",
        )
    with pytest.raises(ValueError, match="folder name"):
        SutureChainConfig(
            subtask_policies=dict.fromkeys(("insert", "extract", "lay_down", "pick_up"), "../up"),
            device="cpu",
        )
    with pytest.raises(ValueError, match="release_radius"):
        SutureChainConfig(
            subtask_policies=dict.fromkeys(("insert", "extract", "lay_down", "pick_up"), "all"),
            release_radius=0.0,
            device="cpu",
        )


def test_each_policy_reads_the_environment_state_it_was_trained_on():
    marks, subtasks = torch.ones(2, MARKS_DIM), torch.zeros(2, SUBTASK_DIM)
    target = torch.full((2, REGRASP_TARGET_DIM), 2.0)
    parts = {"marks": marks, "subtask": subtasks, "regrasp_target": target}
    assert environment_state_for(0, parts) is None
    assert torch.equal(environment_state_for(MARKS_DIM, parts), marks)
    assert torch.equal(environment_state_for(SUBTASK_DIM, {"subtask": subtasks}), subtasks)
    both = environment_state_for(MARKS_DIM + SUBTASK_DIM, parts)
    assert both.shape == (2, MARKS_DIM + SUBTASK_DIM) and torch.equal(both[:, :MARKS_DIM], marks)
    every = environment_state_for(MARKS_DIM + SUBTASK_DIM + REGRASP_TARGET_DIM, parts)
    assert torch.equal(every, torch.cat([marks, subtasks, target], dim=-1))
    assert torch.equal(
        environment_state_for(SUBTASK_DIM + REGRASP_TARGET_DIM, parts)[:, SUBTASK_DIM:], target
    )
    with pytest.raises(ValueError, match="--env.marks=true"):
        environment_state_for(MARKS_DIM, {"subtask": subtasks})
    with pytest.raises(ValueError, match="--env.regrasp_target=true"):
        environment_state_for(MARKS_DIM + REGRASP_TARGET_DIM, {"marks": marks, "subtask": subtasks})
    with pytest.raises(ValueError, match="7 entries"):
        environment_state_for(7, parts)


def test_the_command_refuses_a_subtask_without_a_policy_and_a_used_directory(tmp_path, subtask_policies):
    conditioned, _ = subtask_policies
    with pytest.raises(ValueError, match="--output_dir"):
        ChainCommandConfig(policy=conditioned)
    with pytest.raises(ValueError, match=r"No policy for the subtasks \['insert', 'lay_down', 'pick_up'\]"):
        ChainCommandConfig(output_dir=tmp_path / "chain", extract=conditioned)
    with pytest.raises(FileNotFoundError, match="no config.json"):
        ChainCommandConfig(output_dir=tmp_path / "chain", policy=tmp_path)
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "x").write_text("")
    with pytest.raises(ValueError, match="not empty"):
        ChainCommandConfig(output_dir=tmp_path / "used", policy=conditioned)


def test_the_chain_is_one_directory_that_lerobot_loads_and_the_env_serves(tmp_path, subtask_policies, capsys):
    conditioned, plain = subtask_policies
    out = tmp_path / "chain"
    main([f"--policy={conditioned}", f"--extract={plain}", f"--output_dir={out}"])
    assert "lerobot-eval --policy.path=" in capsys.readouterr().out
    config = json.loads((out / "config.json").read_text())
    assert config["type"] == "suture_chain"
    assert config["subtask_policies"] == {
        "insert": "insert",
        "extract": "extract",
        "lay_down": "insert",
        "pick_up": "insert",
    }
    assert (out / "policies" / "insert" / "model.safetensors").is_file()
    assert (out / "policy_preprocessor.json").is_file()
    chain, _, _ = load_policy(out)
    assert chain.config.input_features[OBS_ENV_STATE].shape == (MARKS_DIM,)
    kwargs = env_kwargs_for_policy(chain.config)
    assert kwargs.get("marks") is True and not kwargs.get("subtask")


def test_each_env_takes_the_action_of_its_own_subtasks_policy(tmp_path, subtask_policies):
    """Two envs hold the needle at the entry mark; the first lets go (its insert ends: extract). From that step
    its action is the plain policy's, predicted afresh, while the second env's stays the conditioned policy's,
    from the chunk it queued, and the conditioned policy reads the subtask after the marks."""
    conditioned, plain = subtask_policies
    out = write_chain(ChainCommandConfig(output_dir=tmp_path / "chain", policy=conditioned, extract=plain))
    chain, pre, post = load_policy(out)
    refs = {name: load_policy(out / "policies" / name) for name in ("insert", "extract")}
    rng = np.random.default_rng(0)
    entry = np.array([-0.008, -0.009, 0.0], dtype=np.float32)
    chain.reset()
    for ref, _, _ in refs.values():
        ref.reset()

    def reference(name: str, batch: dict, readings: list[tuple[str, int]]) -> torch.Tensor:
        ref, ref_pre, ref_post = refs[name]
        sub = dict(batch)
        if name == "insert":  # the conditioned policy: marks, then subtask and throw
            vectors = torch.from_numpy(np.stack([subtask_vector(*r) for r in readings]))
            sub[OBS_ENV_STATE] = torch.cat([batch[OBS_ENV_STATE], vectors], dim=-1)
        else:
            sub.pop(OBS_ENV_STATE)
        return ref_post(ref.select_action(ref_pre(sub)))

    first = _batch([HELD, HELD], entry, rng)
    action = post(chain.select_action(pre(dict(first))))
    assert chain.readings == [("insert", 0), ("insert", 0)]
    assert torch.allclose(action, reference("insert", first, chain.readings), atol=1e-6)

    second = _batch([0.0, HELD], entry, rng)  # env 0 lets go at the entry mark
    action = post(chain.select_action(pre(dict(second))))
    assert chain.readings == [("extract", 0), ("insert", 0)]
    refs["extract"][0].reset()  # the chain starts the policy an env enters afresh
    expected_extract = reference("extract", second, chain.readings)
    expected_insert = reference("insert", second, chain.readings)
    assert torch.allclose(action[0], expected_extract[0], atol=1e-6)
    assert torch.allclose(action[1], expected_insert[1], atol=1e-6)
    assert not torch.allclose(action[0], expected_insert[0], atol=1e-4)

    chain.reset()  # a new episode: the rules start over from the first measured pose
    post(chain.select_action(pre(_batch([0.0, HELD], entry, rng))))
    assert chain.readings == [("pick_up", 0), ("insert", 0)]


def test_a_chain_is_not_trained(tmp_path, subtask_policies):
    conditioned, _ = subtask_policies
    chain, _, _ = load_policy(write_chain(ChainCommandConfig(output_dir=tmp_path / "c", policy=conditioned)))
    with pytest.raises(NotImplementedError, match="lerobot-suture chain"):
        chain.get_optim_params()
    with pytest.raises(NotImplementedError, match="select_action"):
        chain.predict_action_chunk({})


@pytest.mark.slow
def test_lerobot_eval_runs_the_chain_on_the_running_suture(tmp_path, subtask_policies):
    from test_ensemble_eval import check_eval_info, run_lerobot_eval

    conditioned, plain = subtask_policies
    chain = write_chain(ChainCommandConfig(output_dir=tmp_path / "chain", policy=conditioned, extract=plain))
    info, _ = run_lerobot_eval(
        [
            f"--policy.path={chain}",
            "--env.task=running_suture",
            "--env.marks=true",
            "--env.episode_length=8",
            "--eval.n_episodes=2",
            "--eval.batch_size=2",
        ],
        tmp_path / "eval",
    )
    assert check_eval_info(info, n_episodes=2, batch_size=2) == [False, False]


def test_the_robot_reports_the_marks_after_the_pose_and_the_chain_splits_them(tmp_path, subtask_policies):
    """``--robot.marks=true``: the env's marks as ``*.pos`` scalars after the pose, which LeRobot stacks into
    ``observation.state`` (16,); the chain reads the same subtasks and acts the same as from the env path's split."""
    from lerobot_policy_suture_chain.modeling_suture_chain import state_apart
    from lerobot_robot_suture.config_suture_sim import MARK_FEATURES, POSE_FEATURES, SutureSimConfig
    from lerobot_robot_suture.suture_sim import SutureSim

    robot = SutureSim(SutureSimConfig(task="running_suture", marks=True, clock="fast", seed=3))
    assert list(robot.observation_features)[:16] == [*POSE_FEATURES, *MARK_FEATURES]
    robot.connect()
    try:
        observation = robot.get_observation()
        marks = robot.env.unwrapped.entry_point.tolist() + robot.env.unwrapped.exit_point.tolist()
        assert [observation[key] for key in MARK_FEATURES] == pytest.approx(marks, abs=1e-6)
    finally:
        robot.disconnect()

    conditioned, plain = subtask_policies
    out = write_chain(ChainCommandConfig(output_dir=tmp_path / "chain", policy=conditioned, extract=plain))
    rng = np.random.default_rng(1)
    entry = np.array([-0.008, 0.003, 0.0], dtype=np.float32)
    split = [_batch([HELD], entry, rng), _batch([0.0], entry, rng)]
    stacked = [{**b, OBS_STATE: torch.cat([b[OBS_STATE], b[OBS_ENV_STATE]], dim=-1)} for b in split]
    for b in stacked:
        b.pop(OBS_ENV_STATE)
    assert torch.equal(state_apart(stacked[0], MARKS_DIM)[OBS_ENV_STATE], split[0][OBS_ENV_STATE])
    actions = {}
    for name, batches in (("split", split), ("stacked", stacked)):
        torch.manual_seed(0)
        chain, pre, post = load_policy(out)
        chain.reset()
        actions[name] = [post(chain.select_action(pre(dict(b)))) for b in batches]
        assert chain.readings == [("extract", 0)]
    for a, b in zip(actions["split"], actions["stacked"], strict=True):
        assert torch.allclose(a, b, atol=1e-6)


@pytest.mark.slow
def test_lerobot_rollout_runs_the_chain_on_the_arm_with_its_marks(tmp_path, subtask_policies):
    from robot_commands import read_trace, robot_args, run_command

    conditioned, plain = subtask_policies
    chain = write_chain(ChainCommandConfig(output_dir=tmp_path / "chain", policy=conditioned, extract=plain))
    trace = tmp_path / "trace.jsonl"
    run_command(
        "lerobot-rollout",
        [
            "--strategy.type=base",
            f"--policy.path={chain}",
            "--device=cpu",
            "--fps=10",
            "--duration=1.5",
            "--return_to_initial_position=false",
            "--play_sounds=false",
            "--task=running suture",
            *robot_args(trace, "--robot.task=running_suture", "--robot.marks=true", "--robot.seed=5"),
        ],
    )
    steps = read_trace(trace)
    assert len(steps) >= 5 and {line["seed"] for line in steps} == {5}


def test_a_policy_that_reads_the_planned_regrasp_gets_it_from_the_env_and_the_robot(
    tmp_path, subtask_policies
):
    """An extract policy trained with ``regrasp_target=True``: the chain asks the env for the planned regrasp after
    the marks, hands the policy marks, subtask and regrasp in the env's order, and reads the same from the robot
    path, where ``--robot.regrasp_target=true`` reports it after the marks in ``observation.state`` (25,)."""
    from lerobot_policy_suture_chain.modeling_suture_chain import state_apart
    from lerobot_robot_suture.config_suture_sim import (
        MARK_FEATURES,
        POSE_FEATURES,
        REGRASP_TARGET_FEATURES,
        SutureSimConfig,
    )
    from lerobot_robot_suture.suture_sim import SutureSim

    from lerobot_suture.sim.regrasp_target import env_regrasp_target

    conditioned, _ = subtask_policies
    every = MARKS_DIM + SUBTASK_DIM + REGRASP_TARGET_DIM
    regrasp = _save_act(
        tmp_path / "regrasp",
        2,
        {**SUTURE_INPUT_FEATURES, OBS_ENV_STATE: PolicyFeature(FeatureType.ENV, (every,))},
    )
    out = write_chain(ChainCommandConfig(output_dir=tmp_path / "chain", policy=conditioned, extract=regrasp))
    chain, pre, post = load_policy(out)
    assert chain.config.input_features[OBS_ENV_STATE].shape == (MARKS_DIM + REGRASP_TARGET_DIM,)
    kwargs = env_kwargs_for_policy(chain.config)
    assert kwargs.get("marks") is True and kwargs.get("regrasp_target") is True and not kwargs.get("subtask")

    robot = SutureSim(
        SutureSimConfig(task="extraction", marks=True, regrasp_target=True, clock="fast", seed=3)
    )
    names = [*POSE_FEATURES, *MARK_FEATURES, *REGRASP_TARGET_FEATURES]
    assert list(robot.observation_features)[: len(names)] == names
    robot.connect()
    try:
        observation = robot.get_observation()
        pose = np.array([observation[key] for key in POSE_FEATURES])
        expected = env_regrasp_target(robot.env, pose)
        assert [observation[key] for key in REGRASP_TARGET_FEATURES] == pytest.approx(
            expected.tolist(), abs=1e-6
        )
    finally:
        robot.disconnect()

    rng = np.random.default_rng(2)
    entry = np.array([-0.008, 0.003, 0.0], dtype=np.float32)
    target = torch.from_numpy(rng.normal(0, 0.01, (1, REGRASP_TARGET_DIM)).astype(np.float32))
    split = [_batch([HELD], entry, rng), _batch([0.0], entry, rng)]  # the second lets go: extract
    for b in split:
        b[OBS_ENV_STATE] = torch.cat([b[OBS_ENV_STATE], target], dim=-1)
    stacked = [
        {OBS_STATE: torch.cat([b[OBS_STATE], b[OBS_ENV_STATE]], -1), IMAGE_KEY: b[IMAGE_KEY]} for b in split
    ]
    assert torch.equal(
        state_apart(stacked[1], MARKS_DIM + REGRASP_TARGET_DIM)[OBS_ENV_STATE], split[1][OBS_ENV_STATE]
    )
    with pytest.raises(ValueError, match="--robot.marks=true --robot.regrasp_target=true"):
        state_apart({OBS_STATE: torch.zeros(1, 16)}, MARKS_DIM + REGRASP_TARGET_DIM)  # the marks alone
    ref, ref_pre, ref_post = load_policy(out / "policies" / "extract")
    ref.reset()
    marks = split[1][OBS_ENV_STATE][:, :MARKS_DIM]
    vector = torch.from_numpy(subtask_vector("extract", 0))[None]
    sub = {**split[1], OBS_ENV_STATE: torch.cat([marks, vector, target], dim=-1)}
    expected = ref_post(ref.select_action(ref_pre(sub)))
    for batches in (split, stacked):
        chain.reset()
        actions = [post(chain.select_action(pre(dict(b)))) for b in batches]
        assert chain.readings == [("extract", 0)]
        assert torch.allclose(actions[1], expected, atol=1e-6)


def test_a_chain_that_reads_the_subtask_from_the_env_resumes_where_the_arm_is_after_a_reset(
    tmp_path, subtask_policies
):
    """Written with `subtask_from_env`, the chain takes each step's subtask and throw from the env's reading (after
    the marks), so a reset mid-suture (a surgeon's hand-back) leaves it at the arm's subtask and throw, where its
    own rules would start over at the first throw's insert; the robot path and other thresholds are refused."""
    conditioned, plain = subtask_policies
    out = write_chain(
        ChainCommandConfig(
            output_dir=tmp_path / "chain", policy=conditioned, extract=plain, subtask_from_env=True
        )
    )
    chain, pre, post = load_policy(out)
    assert env_kwargs_for_policy(chain.config)["subtask"] is True
    rng = np.random.default_rng(0)
    batch = _batch([HELD], np.array([-0.008, -0.009, 0.0], dtype=np.float32), rng)
    marks = batch[OBS_ENV_STATE]
    chain.reset()
    batch[OBS_ENV_STATE] = torch.cat([marks, torch.from_numpy(subtask_vector("lay_down", 2))[None]], dim=-1)
    post(chain.select_action(pre(dict(batch))))
    assert chain.readings == [
        ("lay_down", 2)
    ]  # the rules, from this pose (the needle held), would say insert 0

    chain.reset()  # a surgeon did the third throw's extract and hands back
    batch[OBS_ENV_STATE] = torch.cat([marks, torch.from_numpy(subtask_vector("extract", 2))[None]], dim=-1)
    action = post(chain.select_action(pre(dict(batch))))
    assert chain.readings == [("extract", 2)]
    ref, ref_pre, ref_post = load_policy(out / "policies" / "extract")
    ref.reset()
    plain_batch = {k: v for k, v in batch.items() if k != OBS_ENV_STATE}
    assert torch.allclose(action, ref_post(ref.select_action(ref_pre(plain_batch))), atol=1e-6)

    robot_batch = {
        OBS_STATE: torch.cat([batch[OBS_STATE], batch[OBS_ENV_STATE]], dim=-1),
        IMAGE_KEY: batch[IMAGE_KEY],
    }
    with pytest.raises(ValueError, match="subtask_from_env=true"):
        chain.select_action(pre(robot_batch))
    with pytest.raises(ValueError, match="default thresholds"):
        ChainCommandConfig(
            output_dir=tmp_path / "c2", policy=conditioned, subtask_from_env=True, release_radius=0.02
        )
    bad = dict(batch, **{OBS_ENV_STATE: torch.cat([marks, torch.zeros(1, 5)], dim=-1)})
    with pytest.raises(ValueError, match="one-hot"):
        chain.select_action(pre(bad))


def test_the_chain_reports_the_gate_of_the_policy_that_acted_for_each_env(
    tmp_path, subtask_policies, tiny_policy_dir
):
    """A stage gate reads the chain's scores per env: the ensemble's where the ensemble gave that env's action,
    silent where a policy without a gate (ACT) did."""
    conditioned, _ = subtask_policies
    out = write_chain(
        ChainCommandConfig(output_dir=tmp_path / "chain", policy=conditioned, extract=tiny_policy_dir)
    )
    chain, pre, post = load_policy(out)
    rng = np.random.default_rng(0)
    entry = np.array([-0.008, -0.009, 0.0], dtype=np.float32)
    chain.reset()
    post(chain.select_action(pre(_batch([HELD, HELD], entry, rng))))
    assert all(np.isnan(chain.ood_status(i)["score"]) for i in (0, 1))
    post(chain.select_action(pre(_batch([0.0, HELD], entry, rng))))  # env 0 lets go: the ensemble extracts
    assert chain.serving == ["extract", "insert"]
    status = chain.ood_status(0)
    assert status["new_prediction"] and np.isfinite(status["score"]) and status["score"] >= 0
    assert status == chain.policies["extract"].ood_status(0)
    assert np.isnan(chain.ood_status(1)["score"]) and not chain.ood_status(1)["new_prediction"]
    assert np.isnan(chain.ood_status(5)["score"])  # an env the chain has not seen
