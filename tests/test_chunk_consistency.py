"""The gate for any chunking policy: STAC on the chunks a real LeRobot ACT predicts, its calibration file, and the
one latched gate it shares with the ensemble on the env path and the robot path."""

import math

import numpy as np
import pytest
import torch

from lerobot_suture.safety.ood.calibration_file import StacCalibration
from lerobot_suture.safety.ood.chunk_consistency import ChunkCapture, ChunkConsistencyMonitor, chunk_source
from lerobot_suture.safety.ood.gate import ChunkGate, OODGate


def tiny_act():
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.act.modeling_act import ACTPolicy
    from policy_builders import tiny_act_config

    torch.manual_seed(0)
    features = {
        "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(10,)),
        "observation.images.endoscope": PolicyFeature(type=FeatureType.VISUAL, shape=(3, 32, 32)),
    }
    return ACTPolicy(tiny_act_config(features)).eval()


def batch(step: int) -> dict:
    generator = torch.Generator().manual_seed(step)
    return {
        "observation.state": torch.randn(1, 10, generator=generator),
        "observation.images.endoscope": torch.rand(1, 3, 32, 32, generator=generator),
    }


def test_stac_scores_the_chunks_a_real_act_predicts():
    policy = tiny_act()
    owner, method, start = chunk_source(policy)
    assert (owner, method, start) == (policy, "predict_action_chunk", 0)
    capture = ChunkCapture(owner, method)
    gate = ChunkGate(ChunkConsistencyMonitor(shift=policy.config.n_action_steps, start=start))
    with torch.inference_mode():
        for step in range(12):
            policy.select_action(batch(step))
            if capture.chunks > len(gate.scores):
                gate.update(capture.last)
    # One chunk per n_action_steps actions, the first of the episode scored 0, the others > 0 (new inputs).
    scores = gate.scores
    assert capture.chunks == 3 and capture.last.shape == (1, 8, 10)
    assert scores[0] == 0.0 and all(s > 0 for s in scores[1:]) and gate.gate.running_max == max(scores)
    assert not gate.flagged, "without a calibration the gate records scores and never flags"
    capture.release()
    assert policy.predict_action_chunk.__func__ is type(policy).predict_action_chunk


def test_identical_chunks_are_consistent_and_a_jump_is_not():
    monitor = ChunkConsistencyMonitor(shift=4, start=0, bandwidth=0.5)
    plan = np.linspace(0, 1, 12)[None, :, None] * np.ones((1, 12, 3))
    monitor.score(plan[:, :8])
    assert monitor.score(plan[:, 4:12]) == pytest.approx(0.0, abs=1e-12)  # kept to its plan
    assert monitor.score(plan[:, 4:12] + 2.0) > 0.5  # a new plan for the same steps


def test_the_one_gate_latches_stac_on_the_episode_maximum_and_fails_safe_on_nan():
    """STAC's calibration is tested per episode by the ensemble's gate: the running maximum against the
    threshold, latched until reset; a NaN chunk score (a broken prediction) flags."""
    calibration = StacCalibration(threshold=0.5, episodes=100, n_action_steps=4)
    assert calibration.mode == "per_episode"
    gate = OODGate(calibration=calibration)
    decisions = [gate.update(score) for score in (0.0, 0.2, 0.7, 0.1)]
    assert decisions == [False, False, True, True] and gate.released and gate.released_at == 2
    assert math.isnan(gate.last_statistic), "STAC's calibration has no I.D. model to standardize against"
    gate.reset()
    assert not gate.released and not gate.update(0.4)
    assert gate.update(math.nan) and gate.released
    with pytest.raises(TypeError, match="chunk detector"):
        ChunkGate(object(), calibration)


def test_calibration_file_round_trips_and_rejects_bad_values(tmp_path):
    calibration = StacCalibration(threshold=0.01, episodes=100, policy_type="act", n_action_steps=4)
    calibration.save(tmp_path)
    assert StacCalibration.load(tmp_path) == calibration
    with pytest.raises(FileNotFoundError, match="calibrate-stac"):
        StacCalibration.load(tmp_path / "missing")
    with pytest.raises(ValueError, match="threshold"):
        StacCalibration(threshold=float("nan"))
    with pytest.raises(ValueError, match="alpha"):
        StacCalibration(threshold=0.1, alpha=0.7)


def test_the_rollout_gate_watches_an_act_with_stac(tmp_path):
    """``RolloutGate`` picks STAC for an ACT with a calibration beside it, and flags once the episode's
    running maximum crosses the threshold; a calibration fitted at another chunk shift is refused."""
    from lerobot_robot_suture.config_suture_sim import CAMERA, POSE_FEATURES
    from lerobot_robot_suture.rollout_gate import RolloutGate

    policy = tiny_act()
    StacCalibration(threshold=1e-12, policy_type="act", n_action_steps=4).save(tmp_path)
    gate = RolloutGate(policy, "auto", tmp_path, camera=None)
    assert gate.kind == "stac"
    observation = {**dict.fromkeys(POSE_FEATURES, 0.0), CAMERA: np.zeros((32, 32, 3), np.uint8)}
    readings = []
    with torch.inference_mode():
        for step in range(9):
            policy.select_action(batch(step))
            readings.append(gate.read(observation))
    assert [r.new_prediction for r in readings] == [True, False, False, False] * 2 + [True]
    assert not readings[0].decision and readings[4].decision and readings[8].decision  # latched
    gate.reset()
    assert not gate.read(observation).decision
    gate.close()
    StacCalibration(threshold=0.1, policy_type="act", n_action_steps=2).save(tmp_path)
    with pytest.raises(ValueError, match="n_action_steps"):
        RolloutGate(tiny_act(), "stac", tmp_path)


def test_calibrate_stac_fits_the_env_path_gate_and_the_rollout_gate_reads_it(tmp_path):
    """``lerobot-suture calibrate-stac`` on a real checkpoint: STAC's gate on the env path's one episode loop,
    a threshold at the conformal quantile of the episodes' maxima, read back by the robot path's gate."""
    import json

    from lerobot_robot_suture.rollout_gate import RolloutGate
    from policy_builders import save_untrained_act_policy

    from lerobot_suture.cli import main as cli_main
    from lerobot_suture.runtime.calibration import STAC_REPORT_FILE
    from lerobot_suture.runtime.policy import GateMode, PolicyRunner

    policy_dir = save_untrained_act_policy(tmp_path / "act")
    cli_main(
        [
            "calibrate-stac",
            f"--policy.path={policy_dir}",
            "--calibration_episodes=2",
            "--holdout_episodes=1",
            "--alpha=0.4",
        ]
    )
    calibration = StacCalibration.load(policy_dir)
    report = json.loads((policy_dir / STAC_REPORT_FILE).read_text())
    assert calibration.episodes == 2 and calibration.policy_type == "act"
    assert calibration.threshold > 0, "the untrained ACT's chunks change from one to the next"
    assert len(report["calibration_seeds"]) == 2 and len(report["holdout_seeds"]) == 1
    runner = PolicyRunner.from_pretrained(policy_dir, GateMode.REPORT)
    gate = RolloutGate(runner.policy, "stac", policy_dir)
    assert gate.kind == "stac" and gate.read({}).threshold == calibration.threshold
    gate.close()
