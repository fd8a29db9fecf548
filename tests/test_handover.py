"""Policy rollouts with the O.O.D. gate at the env step, handover to the surgeon, and calibration."""

import json
import re
import shutil

import gymnasium as gym
import numpy as np
import pytest

from lerobot_suture.cli import main as cli_main
from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy
from lerobot_suture.runtime.rollout import (
    HOLD,
    POLICY,
    SURGEON,
    rollout_episode,
    rollout_episodes,
    rollout_seeds,
)
from lerobot_suture.safety.ood.calibration import fit_calibration
from lerobot_suture.safety.ood.calibration_file import load_calibration, save_calibration
from lerobot_suture.sim.tasks import task_spec


def _runner(policy_dir, tmp_path, threshold: float | None, enforce: bool) -> PolicyRunner:
    directory = tmp_path / "policy"
    shutil.copytree(policy_dir, directory)
    if threshold is not None:
        scores = threshold * (1 + 1e-3 * np.random.default_rng(0).standard_normal(100))
        save_calibration(fit_calibration(np.abs(scores)), directory)
    return PolicyRunner.from_pretrained(directory, GateMode.of(enforce))


def _env(runner, **kwargs):
    return gym.make(
        task_spec(kwargs.get("task", "insertion")).gym_id,
        disable_env_checker=True,
        **env_kwargs_for_policy(runner.policy.config),
        **kwargs,
    )


@pytest.mark.parametrize("relative_actions", [False, True])
def test_forced_ood_hands_over_to_the_expert_which_finishes_the_insertion(
    tiny_policy_dir, tmp_path, relative_actions
):
    runner = _runner(tiny_policy_dir, tmp_path, threshold=1e-12, enforce=True)
    env = _env(runner, relative_actions=relative_actions)  # the surgeon's absolute targets reach either
    log = rollout_episode(env, runner, seed=0, surgeon="expert")
    assert log.handover_step == 0
    assert all(step.controller == SURGEON for step in log.steps)
    assert log.steps[0].released and log.steps[0].ood and log.handover_cause == "gate"
    # The released policy is not asked again: its gate reports nothing after the release.
    assert not any(step.consulted for step in log.steps[1:]) and np.isnan(log.steps[1].score)
    assert log.handovers[0][3] == "gate released" and log.stop_reason == "env"
    assert log.success and not log.autonomous_success


class _JawPoses(gym.Wrapper):
    """Records the measured jaw pose after the reset and after every step."""

    def reset(self, **kwargs):
        out = super().reset(**kwargs)
        self.poses = [self.unwrapped.jaw_pose()]
        return out

    def step(self, action):
        out = super().step(action)
        self.poses.append(self.unwrapped.jaw_pose())
        return out


@pytest.mark.parametrize("relative_actions", [False, True])
def test_with_no_surgeon_the_released_arm_holds_still(tiny_policy_dir, tmp_path, relative_actions):
    runner = _runner(tiny_policy_dir, tmp_path, threshold=1e-12, enforce=True)
    env = _JawPoses(_env(runner, relative_actions=relative_actions))
    log = rollout_episode(env, runner, seed=1, surgeon="none", max_steps=12)
    assert [step.controller for step in log.steps] == [HOLD] * 12
    # The hold action is the pose measured at the release, so the jaw stays there: micrometres, not the
    # millimetres a slow drift or a replayed policy action would move it (the safe set is 8 mm wide).
    released_pos, released_rot = env.poses[log.handover_step]
    for pos, rot in env.poses[log.handover_step :]:
        assert np.linalg.norm(pos - released_pos) < 1e-5
        assert np.linalg.norm(rot - released_rot) < 1e-4
    assert not log.success


def test_reporting_gate_keeps_the_policy_in_control(tiny_policy_dir, tmp_path):
    runner = _runner(tiny_policy_dir, tmp_path, threshold=1e-12, enforce=False)
    log = rollout_episode(_env(runner), runner, seed=0, surgeon="expert", max_steps=9)
    assert log.handover_step is None
    assert all(step.controller == POLICY for step in log.steps)
    assert log.first_alarm_step == 0
    predictions = [step.new_prediction for step in log.steps]
    assert predictions[0] and sum(predictions) == -(-9 // runner.policy.config.n_action_steps)


def test_batched_rollout_keeps_one_gate_and_one_surgeon_per_env(tiny_policy_dir, tmp_path):
    runner = _runner(tiny_policy_dir, tmp_path, threshold=1e-12, enforce=True)
    envs = [_env(runner) for _ in range(3)]
    logs = rollout_episodes(envs, runner, [0, 1, 2], surgeon="expert")
    assert [log.seed for log in logs] == [0, 1, 2]
    for log in logs:
        # Every env was handed over at once and the expert finished its own insertion.
        assert log.handover_step == 0 and log.success
        assert all(step.controller == SURGEON for step in log.steps)
    # Each episode ended on its own step and was not stepped after: the lengths are the expert's.
    singles = [rollout_episode(_env(runner), runner, seed, surgeon="expert") for seed in (0, 1, 2)]
    assert [len(log.steps) for log in logs] == [len(log.steps) for log in singles]


def test_batched_rollouts_are_seeded_and_match_in_batches(tiny_policy_dir, tmp_path):
    runner = _runner(tiny_policy_dir, tmp_path, threshold=1.0, enforce=False)

    def make_env():
        return _env(runner, max_episode_steps=8)

    first = rollout_seeds(make_env, runner, [5, 6, 7], batch_envs=2)
    again = rollout_seeds(make_env, runner, [5, 6, 7], batch_envs=2)
    assert [log.seed for log in first] == [5, 6, 7]
    assert [len(log.steps) for log in first] == [8, 8, 8]
    for a, b in zip(first, again, strict=True):
        np.testing.assert_array_equal(a.scores, b.scores)
    # Rows of one batch see different observations and noise: the scores are the policy's, not a constant.
    assert not np.array_equal(first[0].scores, first[1].scores)
    with pytest.raises(ValueError, match="batch_envs"):
        rollout_seeds(make_env, runner, [5], batch_envs=0)
    with pytest.raises(ValueError, match="one seed per env"):
        rollout_episodes([make_env()], runner, [1, 2])


def test_a_seed_gives_the_same_episode_at_any_batch_size(tiny_policy_dir, tmp_path):
    """Each episode's diffusion noise comes from its own seed: batching is an exact speed-up."""
    runner = _runner(tiny_policy_dir, tmp_path, threshold=1.0, enforce=False)

    def make_env():
        return _env(runner, max_episode_steps=8)

    single = rollout_seeds(make_env, runner, [5, 6, 7], batch_envs=1)
    batched = rollout_seeds(make_env, runner, [5, 6, 7], batch_envs=3)
    shuffled = rollout_seeds(make_env, runner, [7, 5, 6], batch_envs=2)
    shuffled = sorted(shuffled, key=lambda log: [5, 6, 7].index(log.seed))
    for a, b, c in zip(single, batched, shuffled, strict=True):
        assert a.seed == b.seed == c.seed
        # The same chunks up to float rounding (a batched GEMM may sum in another order).
        np.testing.assert_allclose(a.scores, b.scores, rtol=1e-4, atol=1e-9)
        np.testing.assert_allclose(a.scores, c.scores, rtol=1e-4, atol=1e-9)
    # A seed's noise is its own: two seeds in one batch still differ.
    assert not np.allclose(batched[0].scores, batched[1].scores)


@pytest.mark.slow  # multi-process or training: make test-slow
def test_worker_processes_give_the_same_episodes(tiny_policy_dir, tmp_path):
    import functools

    runner = _runner(tiny_policy_dir, tmp_path, threshold=1.0, enforce=False)
    make_env = functools.partial(_env, runner, max_episode_steps=6)
    local = rollout_seeds(make_env, runner, [5, 6, 7], batch_envs=1)
    spread = rollout_seeds(make_env, runner, [5, 6, 7], batch_envs=1, workers=2)
    assert [log.seed for log in spread] == [5, 6, 7]
    for a, b in zip(local, spread, strict=True):
        assert (a.success, len(a.steps)) == (b.success, len(b.steps))
        np.testing.assert_allclose(a.scores, b.scores, rtol=1e-4, atol=1e-9)
    with pytest.raises(ValueError, match="pickled"):
        rollout_seeds(lambda: _env(runner), runner, [5, 6], batch_envs=1, workers=2)
    # A calibration written into the policy's directory since reaches the workers: they start afresh.
    from lerobot_suture.runtime import workers

    pool = next(iter(workers._POOLS.values()))
    save_calibration(fit_calibration(np.full(50, 1e-9) + np.arange(50) * 1e-12), runner.source[0])
    enforced = rollout_seeds(make_env, runner.with_gate(GateMode.ENFORCE), [5, 6], batch_envs=1, workers=2)
    assert next(iter(workers._POOLS.values())) is not pool
    assert all(log.handover_step is not None for log in enforced)  # every score is above that threshold
    in_memory = PolicyRunner(runner.policy, runner.preprocessor, runner.postprocessor, GateMode.REPORT)
    with pytest.raises(ValueError, match="from_pretrained"):
        rollout_seeds(make_env, in_memory, [5, 6], batch_envs=1, workers=2)


@pytest.mark.slow
def test_config_overrides_reach_the_policy_and_the_workers(tiny_policy_dir):
    """Fewer denoising steps / more samples per member, chosen at load as lerobot-eval's --policy.FIELD."""
    import functools

    overrides = {"num_inference_steps": 2, "uncertainty_samples_per_member": 2}
    runner = PolicyRunner.from_pretrained(tiny_policy_dir, GateMode.REPORT, overrides=overrides)
    assert runner.policy.config.num_inference_steps == 2
    assert runner.policy.config.uncertainty_samples_per_member == 2
    make_env = functools.partial(_env, runner, max_episode_steps=5)
    local = rollout_seeds(make_env, runner, [3, 4], batch_envs=1)
    spread = rollout_seeds(make_env, runner, [3, 4], batch_envs=1, workers=2)
    plain = rollout_seeds(make_env, PolicyRunner.from_pretrained(tiny_policy_dir, GateMode.REPORT), [3, 4], 1)
    for a, b, c in zip(local, spread, plain, strict=True):
        np.testing.assert_allclose(a.scores, b.scores, rtol=1e-4, atol=1e-9)  # the workers load the overrides
        assert not np.allclose(a.scores, c.scores)  # and they change the policy


def test_config_overrides_that_name_no_field_or_a_bad_value_are_refused(tiny_policy_dir):
    with pytest.raises(ValueError, match="name no field"):
        PolicyRunner.from_pretrained(tiny_policy_dir, GateMode.REPORT, overrides={"num_denoising_steps": 2})
    with pytest.raises(ValueError, match="num_inference_steps"):
        PolicyRunner.from_pretrained(tiny_policy_dir, GateMode.REPORT, overrides={"num_inference_steps": 0})


def test_command_line_overrides_are_read_as_json_or_kept_as_text():
    from lerobot_suture.runtime.policy import parse_overrides

    parsed = parse_overrides(
        ["n_action_steps=8", "down_dims=[32,64]", "noise_scheduler_type=DDIM", "bootstrap=true"]
    )
    assert parsed == {
        "n_action_steps": 8,
        "down_dims": [32, 64],
        "noise_scheduler_type": "DDIM",
        "bootstrap": True,
    }
    for bad in ("n_action_steps", "=8"):
        with pytest.raises(ValueError, match="FIELD=VALUE"):
            parse_overrides([bad])


def test_each_env_sends_its_own_task_instruction(tiny_policy_dir):
    """A language-conditioned policy reads the instruction of the task its env simulates."""
    runner = PolicyRunner.from_pretrained(tiny_policy_dir, GateMode.REPORT)
    sent, preprocess = [], runner.preprocess
    runner.preprocess = lambda observations, tasks=None: sent.append(tasks) or preprocess(observations, tasks)
    envs = [_env(runner, task=task, max_episode_steps=2) for task in ("pickup", "insertion")]
    rollout_episodes(envs, runner, [1, 2])
    assert sent[0] == [task_spec("pickup").instruction, task_spec("insertion").instruction]


def test_episode_noise_needs_one_seed_per_row(tiny_policy_dir, tmp_path):
    runner = _runner(tiny_policy_dir, tmp_path, threshold=None, enforce=False)
    env = _env(runner)
    observation, _ = env.reset(seed=0)
    runner.reset(seeds=[1, 2])
    with pytest.raises(ValueError, match="one seed per env"):
        runner.act_batch([observation])


def test_surgeon_must_be_known(tiny_policy_dir, tmp_path):
    runner = _runner(tiny_policy_dir, tmp_path, threshold=None, enforce=False)
    with pytest.raises(ValueError, match="surgeon"):
        rollout_episode(_env(runner), runner, seed=0, surgeon="resident")


def test_enforcing_without_calibration_fails_at_load_with_the_fix(tiny_policy_dir, tmp_path):
    directory = tmp_path / "policy"
    shutil.copytree(tiny_policy_dir, directory)
    config = json.loads((directory / "config.json").read_text())
    config["ood"]["enforce"] = True
    (directory / "config.json").write_text(json.dumps(config))
    with pytest.raises(FileNotFoundError, match="lerobot-suture calibrate"):
        PolicyRunner.from_pretrained(directory, GateMode.REPORT)


def test_calibrate_command_writes_a_calibration_the_policy_loads(tiny_policy_dir, tmp_path, capsys, caplog):
    directory = tmp_path / "policy"
    shutil.copytree(tiny_policy_dir, directory)
    config_json = (directory / "config.json").read_bytes()
    cli_main(
        [
            "calibrate",
            f"--policy.path={directory}",
            "--calibration_episodes=2",
            "--holdout_episodes=1",
            "--mode=per_prediction",
        ]
    )
    out = capsys.readouterr().out
    assert "threshold" in out and "False alarms on 1 held-out" in out
    # The untrained policy never succeeds: the gate it gets is calibrated on failures, and the user is told.
    assert "succeeded in 0% of its 2 calibration episodes" in caplog.text
    calibration = load_calibration(directory)
    assert calibration.mode == "per_prediction" and calibration.n_samples >= 10
    report = json.loads((directory / "ood_calibration_report.json").read_text())
    assert report["calibration_seeds"] == [1_000_000, 1_000_001]
    runner = PolicyRunner.from_pretrained(directory, GateMode.REPORT)
    assert runner.policy.ood_calibration == calibration
    assert calibration.score_settings == runner.policy.config.score_settings()
    assert (directory / "config.json").read_bytes() == config_json  # no score flags: the config is kept
    # The threshold belongs to the denoising it was fitted with: an approximation is refused, with the way.
    with pytest.raises(ValueError, match="--copy_to=COPY"):
        PolicyRunner.from_pretrained(directory, GateMode.REPORT, overrides={"num_inference_steps": 2})


def test_calibrate_makes_a_calibrated_copy_of_an_approximation(tiny_policy_dir, tmp_path, capsys):
    directory, copy = tmp_path / "policy", tmp_path / "samples_2"
    shutil.copytree(tiny_policy_dir, directory)
    save_calibration(fit_calibration(np.full(50, 1.0) + np.arange(50) * 1e-3), directory)  # as trained
    save_calibration(
        fit_calibration(np.full(50, 2.0) + np.arange(50) * 1e-3), directory, "ood_calibration_rtc.json"
    )
    original = {p.name: p.read_bytes() for p in directory.iterdir()}
    args = ["calibrate", f"--policy.path={directory}", "--policy.uncertainty_samples_per_member=2"]
    cli_main(
        [*args, f"--copy_to={copy}", "--calibration_episodes=2", "--holdout_episodes=0"]
        + ["--mode=per_prediction"]
    )
    assert {p.name: p.read_bytes() for p in directory.iterdir()} == original  # the original is untouched
    runner = PolicyRunner.from_pretrained(copy, GateMode.ENFORCE)  # its own gate, fitted with K = 2
    assert runner.policy.config.uncertainty_samples_per_member == 2
    assert runner.policy.ood_calibration.score_settings["uncertainty_samples_per_member"] == 2
    assert not (copy / "ood_calibration_rtc.json").exists()  # no calibration of the original's goes along
    with pytest.raises(SystemExit):  # nothing already there is overwritten
        cli_main([*args, f"--copy_to={copy}", "--calibration_episodes=2", "--mode=per_prediction"])
    assert "exists and is not empty" in capsys.readouterr().err


def test_calibrate_with_a_score_choice_writes_it_beside_its_calibration(tiny_policy_dir, tmp_path, capsys):
    directory = tmp_path / "policy"
    shutil.copytree(tiny_policy_dir, directory)
    args = ["calibrate", f"--policy.path={directory}", "--calibration_episodes=2", "--holdout_episodes=0"]
    with pytest.raises(SystemExit) as exit_info:
        cli_main([*args, "--uncertainty_source=aleatoric", "--mode=per_prediction"])  # one sample per member
    assert exit_info.value.code == 2
    assert re.search(
        "`uncertainty_source`=.aleatoric. needs `uncertainty_samples_per_member` >= 2",
        capsys.readouterr().err,
    )
    assert json.loads((directory / "config.json").read_text())["uncertainty_source"] == "total"
    cli_main([*args, "--uncertainty_score=trace", "--uncertainty_steps=action", "--mode=per_prediction"])
    runner = PolicyRunner.from_pretrained(directory, GateMode.REPORT)
    config = runner.policy.config
    assert (config.uncertainty_score, config.uncertainty_steps) == ("trace", "action")
    calibration = runner.policy.ood_calibration
    assert calibration.score_name == "trace" and calibration.score_settings["uncertainty_steps"] == "action"


def test_calibrate_rejects_too_few_episodes_for_per_episode_mode(tiny_policy_dir, capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli_main(["calibrate", f"--policy.path={tiny_policy_dir}", "--calibration_episodes=5"])
    assert exit_info.value.code == 2
    assert "needs at least 19 calibration episodes" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["calibrate", "calibrate-stac", "dagger"])
def test_commands_that_write_into_the_policy_refuse_approximations(command, tiny_policy_dir, capsys):
    """A calibration or a fine-tuned policy must hold for the policy as it will be loaded: as trained."""
    with pytest.raises(SystemExit) as exit_info:
        cli_main([command, f"--policy.path={tiny_policy_dir}", "--policy.num_inference_steps=2"])
    assert exit_info.value.code == 2
    assert "drop --policy.num_inference_steps" in capsys.readouterr().err
