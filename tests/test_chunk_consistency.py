"""The gate for any chunking policy: STAC on the chunks a real LeRobot ACT predicts, and its calibration file."""

import numpy as np
import pytest
import torch

from lerobot_suture.safety.ood.chunk_consistency import (
    ChunkCapture,
    ChunkConsistencyMonitor,
    StacCalibration,
    chunk_source,
)


def tiny_act():
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy

    torch.manual_seed(0)
    config = ACTConfig(
        input_features={
            "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(10,)),
            "observation.images.endoscope": PolicyFeature(type=FeatureType.VISUAL, shape=(3, 32, 32)),
        },
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(10,))},
        chunk_size=8,
        n_action_steps=4,
        pretrained_backbone_weights=None,
        dim_model=32,
        n_heads=2,
        dim_feedforward=64,
        n_encoder_layers=1,
        n_vae_encoder_layers=1,
        device="cpu",
    )
    return ACTPolicy(config).eval()


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
    monitor = ChunkConsistencyMonitor(shift=policy.config.n_action_steps, start=start)
    scores = []
    with torch.inference_mode():
        for step in range(12):
            policy.select_action(batch(step))
            if capture.chunks > len(scores):
                scores.append(monitor.update(capture.last))
    # One chunk per n_action_steps actions, the first of the episode scored 0, the others > 0 (new inputs).
    assert capture.chunks == 3 and capture.last.shape == (1, 8, 10)
    assert scores[0] == 0.0 and all(s > 0 for s in scores[1:]) and monitor.episode_max == max(scores)
    capture.release()
    assert policy.predict_action_chunk.__func__ is type(policy).predict_action_chunk


def test_identical_chunks_are_consistent_and_a_jump_is_not():
    monitor = ChunkConsistencyMonitor(shift=4, start=0, bandwidth=0.5)
    plan = np.linspace(0, 1, 12)[None, :, None] * np.ones((1, 12, 3))
    monitor.update(plan[:, :8])
    assert monitor.update(plan[:, 4:12]) == pytest.approx(0.0, abs=1e-12)  # kept to its plan
    assert monitor.update(plan[:, 4:12] + 2.0) > 0.5  # a new plan for the same steps


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
