"""The O.O.D. gate inside EnsembleDiffusionPolicy: reporting, enforcing (hold and latch), errors."""

import math

import numpy as np
import pytest
import torch
from lerobot.utils.constants import OBS_STATE
from lerobot_policy_ensemble_diffusion import EnsembleDiffusionPolicy
from policy_builders import fake_dataset_stats, random_observation, tiny_config

from lerobot_suture.safety.ood.calibration import fit_calibration
from lerobot_suture.safety.ood.calibration_file import CalibrationNotFoundError, save_calibration


def _policy(enforce: bool) -> EnsembleDiffusionPolicy:
    torch.manual_seed(0)
    config = tiny_config(n_members=2, noise_scheduler_type="DDIM", ood={"enforce": enforce})
    return EnsembleDiffusionPolicy(config, dataset_stats=fake_dataset_stats()).eval()


def _calibration(threshold_scale: float):
    """A calibration whose threshold sits at `threshold_scale` (scores ~ N(threshold_scale, tiny))."""
    rng = np.random.default_rng(0)
    scores = threshold_scale * (1 + 1e-3 * rng.standard_normal(200))
    return fit_calibration(np.abs(scores), model="normal")


def _observation(policy, seed=0):
    return random_observation(policy.config, batch_size=1, n_steps=0, seed=seed)  # one env step


def test_reporting_gate_logs_score_and_threshold_and_keeps_control():
    policy = _policy(enforce=False)
    policy.ood_calibration = _calibration(1e-12)  # every score is above: O.O.D. at once
    policy.reset()
    obs = _observation(policy)
    first = policy.select_action(obs)
    status = policy.ood_status(0)
    assert status["new_prediction"] and status["decision"]
    assert not status["released"], "a reporting gate never releases control"
    assert math.isfinite(status["score"]) and status["threshold"] == pytest.approx(1e-12, rel=1e-2)
    second = policy.select_action(obs)
    assert not policy.ood_status(0)["new_prediction"]
    # The policy acts: its first two actions are the first two steps of its predicted chunk, not a hold
    # of the measured pose (which an enforced gate would return).
    prediction = policy.last_prediction
    chunk = prediction.normalized.mean[:, prediction.action_steps]  # (1, n_action_steps, A)
    assert chunk.shape[1] >= 2
    torch.testing.assert_close(torch.stack([first, second], dim=1), chunk[:, :2], rtol=0, atol=0)
    pose_raw = obs[OBS_STATE] * policy.state_unnormalize_scale + policy.state_unnormalize_offset
    for action in (first, second):
        action_raw = action * policy.action_unnormalize_scale + policy.action_unnormalize_offset
        assert not torch.allclose(action_raw, pose_raw, rtol=1e-5, atol=1e-5)


def test_enforced_gate_releases_holds_the_measured_pose_and_latches():
    policy = _policy(enforce=True)
    policy.ood_calibration = _calibration(1e-12)
    policy.reset()
    obs = _observation(policy)
    action = policy.select_action(obs)  # (1, A), normalized
    assert policy.ood_status(0)["released"]
    pose_raw = obs[OBS_STATE] * policy.state_unnormalize_scale + policy.state_unnormalize_offset
    action_raw = action * policy.action_unnormalize_scale + policy.action_unnormalize_offset
    torch.testing.assert_close(action_raw, pose_raw, rtol=1e-5, atol=1e-5)
    # Latched: later steps hold too, even when a new observation would look in-distribution.
    for seed in range(1, policy.config.n_action_steps + 2):
        obs = _observation(policy, seed=seed)
        action = policy.select_action(obs)
        assert policy.ood_status(0)["released"]
        pose_raw = obs[OBS_STATE] * policy.state_unnormalize_scale + policy.state_unnormalize_offset
        action_raw = action * policy.action_unnormalize_scale + policy.action_unnormalize_offset
        torch.testing.assert_close(action_raw, pose_raw, rtol=1e-5, atol=1e-5)
    policy.reset()
    assert not policy.ood_status(0)["released"]


def test_in_distribution_scores_keep_control_with_the_gate_enforced():
    policy = _policy(enforce=True)
    policy.ood_calibration = _calibration(1e9)
    policy.reset()
    for seed in range(3):
        policy.select_action(_observation(policy, seed=seed))
        assert not policy.ood_status(0)["released"] and not policy.ood_status(0)["decision"]


def test_enforcing_without_a_calibration_says_how_to_calibrate():
    policy = _policy(enforce=True)
    with pytest.raises(ValueError, match="lerobot-suture calibrate"):
        policy.select_action(_observation(policy))


def test_calibration_is_loaded_from_the_policy_directory(tmp_path):
    policy = _policy(enforce=False)
    with pytest.raises(CalibrationNotFoundError, match="lerobot-suture calibrate"):
        policy.load_ood_calibration(tmp_path)
    calibration = _calibration(0.5)
    save_calibration(calibration, tmp_path, filename=policy.config.ood.calibration_file)
    assert policy.load_ood_calibration(tmp_path) == calibration
    wrong = fit_calibration(np.abs(np.random.default_rng(1).normal(1, 0.1, 50)), score_name="trace")
    save_calibration(wrong, tmp_path, filename=policy.config.ood.calibration_file)
    with pytest.raises(ValueError, match="fitted on score 'trace'"):
        policy.load_ood_calibration(tmp_path)


def test_calibration_fitted_with_other_score_settings_is_refused(tmp_path):
    policy = _policy(enforce=False)
    scores = np.abs(np.random.default_rng(1).normal(1, 0.1, 50))
    settings = policy.config.score_settings()
    matching = fit_calibration(scores, score_settings=settings)
    save_calibration(matching, tmp_path, filename=policy.config.ood.calibration_file)
    assert policy.load_ood_calibration(tmp_path).score_settings == settings
    other = fit_calibration(scores, score_settings={**settings, "uncertainty_samples_per_member": 8})
    save_calibration(other, tmp_path, filename=policy.config.ood.calibration_file)
    with pytest.raises(ValueError, match="uncertainty_samples_per_member=8 \\(this policy: 1\\)"):
        policy.load_ood_calibration(tmp_path)
    steps = policy.config.n_action_steps
    other = fit_calibration(scores, score_settings={**settings, "n_action_steps": steps + 1})
    save_calibration(other, tmp_path, filename=policy.config.ood.calibration_file)
    with pytest.raises(ValueError, match=f"n_action_steps={steps + 1} \\(this policy: {steps}\\)"):
        policy.load_ood_calibration(tmp_path)
