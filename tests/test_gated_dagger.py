"""``lerobot-rollout --strategy.type=gated_dagger`` on the simulated arm, run as LeRobot's console script: the
gate hands over to the scripted surgeon teleoperator, every action goes through the ``suture_cbf`` step, and
the episodes carry LeRobot's ``intervention`` label and the gate's score and decision."""

import numpy as np
import pytest
from robot_commands import dataset_args, episode_frames, load_dataset, read_trace, robot_args, run_command

from lerobot_suture.safety.cbf import ellipsoid_h
from lerobot_suture.safety.cbf_config import CBFConfig

FROZEN_AT = 4


def gated_dagger(policy_dir, fps: int, *args: str) -> str:
    """``lerobot-rollout --strategy.type=gated_dagger`` with the scripted surgeon, on the CPU at ``fps``, and
    ``args`` (strategy, inference, robot and dataset flags); returns its log."""
    command = [
        "--strategy.type=gated_dagger",
        f"--policy.path={policy_dir}",
        "--teleop.type=suture_scripted",
        "--device=cpu",
        f"--fps={fps}",
        "--return_to_initial_position=false",
        *args,
    ]
    return run_command("lerobot-rollout", command, timeout=600)


def frozen_camera_robot(trace) -> list[str]:
    """The simulated arm of scene 7 whose endoscope freezes at control step ``FROZEN_AT``, traced to ``trace``."""
    return robot_args(
        trace,
        "--robot.seed=7",
        "--robot.clock=fast",
        "--robot.episode_end=hold",
        "--robot.tip_tracking=true",
        "--robot.registration=true",
        f"--robot.faults.frozen_camera_step={FROZEN_AT}",
    )


@pytest.fixture(scope="module")
def frozen_camera_run(tiny_policy_dir, tmp_path_factory):
    """Two episodes; the endoscope freezes at control step 4 of each scene, and the camera watchdog (the only
    gate an uncalibrated policy has) hands over."""
    directory = tmp_path_factory.mktemp("gated_dagger")
    root, trace = directory / "dataset", directory / "trace.jsonl"
    log = gated_dagger(
        tiny_policy_dir,
        200,
        "--strategy.gate=none",
        *frozen_camera_robot(trace),
        *dataset_args(root, "local/rollout_gated", episodes=2, episode_s=60, reset_s=0),
    )
    return root, read_trace(trace), log


def test_the_gate_hands_over_and_the_frames_carry_the_labels(frozen_camera_run):
    root, trace, log = frozen_camera_run
    assert "Gated DAgger: gate none, CBF on" in log
    dataset = load_dataset(root, "local/rollout_gated")
    assert dataset.meta.total_episodes == 2
    for key in ("intervention", "ood_score", "ood_threshold", "ood_decision"):
        assert key in dataset.features
    for episode in range(2):
        frames = episode_frames(dataset, episode)
        intervention = np.array([bool(f["intervention"]) for f in frames])
        decision = np.array([bool(f["ood_decision"]) for f in frames])
        # The policy drives until the watchdog sees the frozen frame while the arm moves, then the surgeon.
        handover = int(np.argmax(intervention))
        assert intervention.any() and not intervention[:handover].any() and intervention[handover:].all()
        assert FROZEN_AT < handover <= FROZEN_AT + 6
        assert decision[handover:].all() and not decision[:handover].any()
        # One frame per executed control step of the scene of seed 7 + episode, which the surgeon finished.
        steps = [line for line in trace if line["seed"] == 7 + episode]
        assert len(frames) == len(steps) and steps[-1]["throw_over"] and steps[-1]["is_success"]


def test_every_action_went_through_the_cbf(frozen_camera_run):
    """The scripted surgeon's throw, through the CBF step: the tip stays in the safe set while it is held."""
    import gymnasium as gym

    _, trace, _ = frozen_camera_run
    cbf = CBFConfig(enabled=True)
    env = gym.make("lerobot_suture/NeedleInsertion-v0", obs_type="state")
    for seed in (7, 8):
        env.reset(seed=seed)
        base = env.unwrapped
        from lerobot_suture.safety.wound import Wound

        center, rotation = Wound(
            base.entry_point, base.exit_point, base.phantom_rotation[:, 2]
        ).ellipsoid_frame()
        tips = np.array(
            [line["needle_tip"] for line in trace if line["seed"] == seed and line["needle_in_tissue"]]
        )
        assert len(tips) > 5
        assert np.all(ellipsoid_h(tips, center, cbf.semi_axes, rotation) >= 0.0)
    env.close()


def test_the_recording_merges_with_the_demonstrations(frozen_camera_run, tmp_path):
    """Expert demonstrations in the recording's layout, merged with it by LeRobot's merge: one dataset that
    loads, with the labels the demonstrations never had filled (no intervention, no score, no decision)."""
    from robot_commands import load_dataset

    from lerobot_suture.datasets.record import record
    from lerobot_suture.datasets.record_config import RecordConfig
    from lerobot_suture.datasets.robot_path_merge import merge_with_demonstrations

    root, _, _ = frozen_camera_run
    demo_root = tmp_path / "demonstrations"
    record(RecordConfig(repo_id="suture-tests/demo", root=str(demo_root), num_episodes=2, val_fraction=0.5))
    demonstrations = load_dataset(demo_root, "suture-tests/demo")
    recording = load_dataset(root, "local/rollout_gated")
    merged = merge_with_demonstrations(demonstrations, recording, tmp_path / "merged", "local/merged")
    assert merged.meta.total_episodes == 4 and merged.meta.robot_type == "suture_sim"
    assert merged.meta.total_frames == demonstrations.meta.total_frames + recording.meta.total_frames
    assert set(merged.features) == set(recording.features)
    first, last = merged[0], merged[merged.meta.total_frames - 1]
    assert not bool(first["intervention"]) and np.isnan(float(first["ood_score"]))
    assert bool(last["intervention"]) and bool(last["ood_decision"])


HANDOVER_SEEDS = (5_000_004, 5_000_005)
"""Seeds on which the tiny policy's gate at threshold 1.995 hands over at step 12, and at once."""


@pytest.fixture(scope="module")
def calibrated_tiny_policy(tiny_policy_dir, tmp_path_factory):
    """The tiny policy with a gate whose threshold sits at 1.995, among its own scores."""
    import shutil

    from lerobot_suture.safety.ood.calibration import fit_calibration
    from lerobot_suture.safety.ood.calibration_file import save_calibration

    directory = tmp_path_factory.mktemp("gated_tiny") / "policy"
    shutil.copytree(tiny_policy_dir, directory)
    scores = 1.995 * (1 + 1e-4 * np.random.default_rng(0).standard_normal(100))
    save_calibration(fit_calibration(scores, model="normal"), directory, filename="ood_calibration.json")
    return directory


def test_handovers_fall_where_the_env_path_s_enforced_gate_hands_over(calibrated_tiny_policy, tmp_path):
    """The ensemble's own gate on the robot path hands over at the step the env path's enforced gate does."""
    from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy
    from lerobot_suture.runtime.rollout import make_scenario_env, rollout_episode

    runner = PolicyRunner.from_pretrained(calibrated_tiny_policy, GateMode.ENFORCE)
    env = make_scenario_env(env_kwargs_for_policy(runner.policy.config), "nominal")
    expected = [rollout_episode(env, runner, seed, surgeon="expert").handover_step for seed in HANDOVER_SEEDS]
    env.close()
    assert expected[0] > 4  # mid-episode: not the first prediction
    root = tmp_path / "dataset"
    log = gated_dagger(
        calibrated_tiny_policy,
        200,
        "--strategy.gate=ensemble",
        "--strategy.cbf.enabled=false",
        *robot_args(
            tmp_path / "trace.jsonl",
            f"--robot.seed={HANDOVER_SEEDS[0]}",
            "--robot.clock=fast",
            "--robot.episode_end=hold",
        ),
        *dataset_args(root, "local/rollout_gated_ensemble", episodes=2, episode_s=60, reset_s=0),
    )
    assert "Gated DAgger: gate ensemble, CBF off" in log
    dataset = load_dataset(root, "local/rollout_gated_ensemble")
    for episode, step in enumerate(expected):
        intervention = np.array([bool(f["intervention"]) for f in episode_frames(dataset, episode)])
        handover = int(np.argmax(intervention)) if intervention.any() else None
        assert (handover is None) == (step is None), (episode, handover, step)
        if step is not None:
            assert abs(handover - step) <= 2, (episode, handover, step)


@pytest.mark.slow
def test_tissue_moving_beyond_the_cbf_s_bounds_hands_over(tiny_policy_dir, tmp_path):
    """The phantom breathes at three times the declared acceleration bound: the CBF step flags it and the
    strategy hands over to the teleoperator, with no gate and no camera watchdog to do it."""
    from lerobot_suture.experiments.attack_episodes import CONDITIONS

    beyond = CONDITIONS["beyond_bound_breathing"]
    root = tmp_path / "dataset"
    log = gated_dagger(
        tiny_policy_dir,
        200,
        "--strategy.gate=none",
        "--strategy.camera_watchdog=false",
        *robot_args(
            tmp_path / "trace.jsonl",
            "--robot.seed=3",
            "--robot.clock=fast",
            "--robot.episode_end=hold",
            "--robot.tip_tracking=true",
            "--robot.registration=true",
            f"--robot.scenario={beyond.scenario}",
            f"--robot.scenario_magnitude={beyond.scenario_magnitude}",
        ),
        *dataset_args(root, "local/rollout_tissue_motion", episodes=1, episode_s=60, reset_s=0),
    )
    assert "the tissue moves beyond its declared bounds" in log
    dataset = load_dataset(root, "local/rollout_tissue_motion")
    intervention = np.array([bool(f["intervention"]) for f in episode_frames(dataset, 0)])
    assert intervention.any() and not intervention[0]


@pytest.mark.slow
def test_gated_dagger_on_lerobot_s_real_time_chunking_engine(tiny_policy_dir, tmp_path):
    """``--inference.type=rtc``: the policy's chunks come from LeRobot's background engine; the camera watchdog
    still hands over after the frozen frame, and no frame the policy drove carries an O.O.D. decision."""
    root = tmp_path / "dataset"
    log = gated_dagger(
        tiny_policy_dir,
        20,
        "--strategy.gate=none",
        "--inference.type=rtc",
        "--inference.rtc.execution_horizon=8",
        *frozen_camera_robot(tmp_path / "trace.jsonl"),
        *dataset_args(root, "local/rollout_gated_rtc", episodes=1, episode_s=60, reset_s=0),
    )
    assert "Creating inference engine: rtc" in log and "Gated DAgger: gate none, CBF on" in log
    frames = episode_frames(load_dataset(root, "local/rollout_gated_rtc"), 0)
    intervention = np.array([bool(f["intervention"]) for f in frames])
    decision = np.array([bool(f["ood_decision"]) for f in frames])
    handover = int(np.argmax(intervention))
    assert intervention.any() and handover > 0 and intervention[handover:].all()
    assert not decision[:handover].any() and decision[handover:].all()


@pytest.mark.slow
def test_an_episode_too_short_for_its_video_is_discarded_and_the_run_goes_on(tiny_policy_dir, tmp_path):
    """An episode of one frame (here: 50 ms at 10 Hz) gets no video statistics from LeRobot's streaming encoder,
    and the dataset's metadata cannot hold it beside longer ones (an ``ArrowInvalid`` at a later save). It is
    discarded with a warning that says why, and the run goes on."""
    root = tmp_path / "dataset"
    log = gated_dagger(
        tiny_policy_dir,
        10,
        "--strategy.gate=none",
        *robot_args(tmp_path / "trace.jsonl", "--robot.seed=7", "--robot.clock=fast"),
        *dataset_args(root, "local/rollout_short", episodes=2, episode_s=0.05, reset_s=0),
    )
    assert log.count("fewer than the 2 a video episode needs: discarded") == 2
    assert "ArrowInvalid" not in log
    assert not (root / "meta" / "episodes").exists()
