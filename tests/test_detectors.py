"""The failure detectors' maths on synthetic data, the failure-prediction balanced accuracy, the shared
per-episode threshold, and the policy's feature capture (its actions unchanged)."""

import math

import numpy as np
import pytest
from lerobot_suture_studies.benchmark_ood_scoring import hold_scores, prediction_features

from lerobot_suture.detectors import (
    DETECTOR_NAMES,
    Detector,
    EnsembleCovarianceDetector,
    EpistemicDetector,
    MahalanobisDetector,
    PredictionFeatures,
    RNDDetector,
    SingleMemberSpreadDetector,
    TemporalConsistencyDetector,
    TrackingErrorDetector,
    make_detector,
    timed_scores,
)
from lerobot_suture.detectors.covariance import ensemble_covariances, sample_covariance
from lerobot_suture.detectors.mahalanobis import fit_gaussian, ledoit_wolf, mahalanobis_distance
from lerobot_suture.detectors.tracking import commanded_target, fit_tracking, tracking_score
from lerobot_suture.experiments.metrics import failure_prediction_balanced_accuracy
from lerobot_suture.safety.ood.calibration import conformal_episode_threshold, fit_calibration
from lerobot_suture.safety.ood.stac_score import chunk_overlap, mmd_squared

N, K, T, A, G = 4, 3, 8, 3, 12


def _features(rng, spread=0.05, shift_embedding=0.0, **kw) -> PredictionFeatures:
    base = rng.normal(size=(T, A))
    defaults = {
        "previous_samples": base + spread * rng.normal(size=(N, K, T, A)),
        "shift": 4,
        "state": rng.normal(size=A),
    }
    return PredictionFeatures(
        samples=base + spread * rng.normal(size=(N, K, T, A)),
        action_start=1,
        embedding=rng.normal(size=(N, G)) + shift_embedding,
        single_member_samples=base + spread * rng.normal(size=(6, T, A)),
        **{**defaults, **kw},
    )


def test_covariance_split_adds_up_and_matches_numpy():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(N, K, T, A))
    epistemic, aleatoric = ensemble_covariances(x)
    np.testing.assert_allclose(epistemic[2], np.cov(x.mean(axis=1)[:, 2].T), atol=1e-12)
    np.testing.assert_allclose(aleatoric[2], np.mean([np.cov(x[n, :, 2].T) for n in range(N)], axis=0))
    assert ensemble_covariances(x[:, :1])[1] is None  # K = 1: the members' own spread is unknown
    with pytest.raises(ValueError, match="at least 2 samples"):
        sample_covariance(x[:1, 0])


@pytest.mark.parametrize(
    "detector", [EnsembleCovarianceDetector(), EpistemicDetector(), SingleMemberSpreadDetector()]
)
def test_spread_detectors_grow_with_the_spread_and_ignore_a_common_offset(detector):
    rng = np.random.default_rng(1)
    calm = [detector.score(_features(rng, spread=0.01)) for _ in range(20)]
    wild = [detector.score(_features(rng, spread=0.3)) for _ in range(20)]
    assert max(calm) < min(wild)
    f = _features(rng)
    moved = PredictionFeatures(
        samples=f.samples + 5.0, action_start=1, single_member_samples=f.single_member_samples + 5.0
    )
    assert detector.score(moved) == pytest.approx(detector.score(f), rel=1e-9)


def test_epistemic_ignores_the_members_own_spread_and_total_does_not():
    rng = np.random.default_rng(2)
    agree = np.broadcast_to(rng.normal(size=(1, 1, T, A)), (N, K, T, A)).copy()
    noisy = agree + 0.3 * rng.normal(size=(N, K, T, A))
    noisy -= noisy.mean(axis=1, keepdims=True) - agree[:, :1]  # every member's mean is the common one
    f = PredictionFeatures(samples=noisy, action_start=1)
    assert EpistemicDetector().score(f) == pytest.approx(0.0, abs=1e-12)
    assert EnsembleCovarianceDetector().score(f) > 0.01


def test_ledoit_wolf_shrinks_more_with_fewer_samples_and_stays_invertible():
    rng = np.random.default_rng(3)
    mix = rng.normal(size=(20, 20))  # a correlated covariance, far from the target mu I
    few = rng.normal(size=(5, 20)) @ mix
    many = rng.normal(size=(2000, 20)) @ mix
    cov_few, rho_few = ledoit_wolf(few - few.mean(0))
    _, rho_many = ledoit_wolf(many - many.mean(0))
    assert 0 <= rho_many < rho_few <= 1
    assert np.linalg.eigvalsh(cov_few).min() > 0  # 5 samples in 20 dimensions, still positive definite


def test_mahalanobis_is_low_in_distribution_high_when_shifted_and_affine_invariant():
    rng = np.random.default_rng(4)
    mix = rng.normal(size=(G, G))
    train = rng.normal(size=(300, G)) @ mix
    fit = fit_gaussian(train)
    inside = mahalanobis_distance(fit, rng.normal(size=(50, G)) @ mix)
    outside = mahalanobis_distance(fit, (rng.normal(size=(50, G)) + 3.0) @ mix)
    assert np.median(inside) < np.median(outside) and np.mean(inside < np.median(outside)) > 0.9
    scale, offset = rng.uniform(0.1, 10, size=G), rng.normal(size=G)
    refit = fit_gaussian(train * scale + offset)
    x = rng.normal(size=(5, G)) @ mix
    np.testing.assert_allclose(mahalanobis_distance(refit, x * scale + offset), mahalanobis_distance(fit, x))


def test_learned_detectors_separate_shifted_embeddings():
    rng = np.random.default_rng(5)
    nominal = [_features(rng) for _ in range(200)]
    for detector in (MahalanobisDetector(), RNDDetector(steps=300)):
        detector.fit(nominal)
        inside = [detector.score(_features(rng)) for _ in range(30)]
        shifted = [detector.score(_features(rng, shift_embedding=4.0)) for _ in range(30)]
        assert np.median(inside) < min(shifted), detector.name


def test_learned_detectors_refuse_to_score_unfitted_or_without_embeddings():
    rng = np.random.default_rng(6)
    with pytest.raises(ValueError, match="not fitted"):
        MahalanobisDetector().score(_features(rng))
    with pytest.raises(ValueError, match="enable_feature_capture"):
        RNDDetector().fit([PredictionFeatures(samples=np.zeros((N, K, T, A)), action_start=1)] * 3)
    with pytest.raises(ValueError, match="`steps` must be >= 1"):
        RNDDetector(steps=0)


def test_chunk_overlap_aligns_the_same_future_control_steps():
    t = np.arange(T, dtype=float)[None, :, None]  # each step holds its own index
    previous, current = t + 100.0, t  # previous made `shift` steps earlier: its index j is time j - shift
    a, b = chunk_overlap(previous, current, shift=3, start=1)
    np.testing.assert_array_equal(a - 100.0 - 3, b)  # same control steps
    assert a.shape == (1, T - 1 - 3, 1)
    with pytest.raises(ValueError, match="do not overlap"):
        chunk_overlap(previous, current, shift=T - 1, start=1)


def test_stac_is_zero_for_a_consistent_plan_and_grows_when_the_plan_changes():
    rng = np.random.default_rng(7)
    plan = np.cumsum(rng.normal(size=(T + 4, A)), axis=0) * 0.1  # one trajectory in control time
    shift, start = 4, 1

    def chunk(at, offset=0.0):  # every member's chunk of the plan from control step `at`
        c = plan[at - start : at - start + T] + offset
        return np.broadcast_to(c, (N, 1, T, A)) + 0.01 * rng.normal(size=(N, 1, T, A))

    detector = TemporalConsistencyDetector()
    keep = PredictionFeatures(chunk(5), start, previous_samples=chunk(1), shift=shift)
    swerve = PredictionFeatures(chunk(5, offset=0.5), start, previous_samples=chunk(1), shift=shift)
    assert detector.score(keep) < 1e-3 < detector.score(swerve)
    assert detector.score(PredictionFeatures(chunk(5), start)) == 0.0  # first prediction: nothing to compare
    x = rng.normal(size=(6, 4, A))
    assert mmd_squared(x, x, 0.5) == pytest.approx(0.0, abs=1e-12)
    assert mmd_squared(x, x + 1.0, 0.5) == pytest.approx(mmd_squared(x + 1.0, x, 0.5))


def _tracking_run(rng, n, lag=0, reading_noise=0.0):
    """Predictions of an arm that reaches the command of ``lag`` steps earlier, its state read in other
    normalized units than the action (s = 2 x + 0.5) with a little tracking noise."""
    out = []
    for _ in range(n):
        previous = np.cumsum(rng.normal(size=(T, A)), axis=0)[None, None] + 0.01 * rng.normal(
            size=(N, K, T, A)
        )
        reached = previous.mean(axis=(0, 1))[1 + 4 - 1 - lag]  # action_start 1, shift 4
        state = 2.0 * reached + 0.5 + 0.01 * rng.normal(size=A) + reading_noise * rng.normal(size=A)
        out.append(_features(rng, previous_samples=previous, shift=4, state=state))
    return out


def test_tracking_error_is_low_when_the_arm_follows_and_high_when_it_lags_or_reads_noisily():
    rng = np.random.default_rng(10)
    detector = TrackingErrorDetector(dims=(0, 1, 2)).fit(_tracking_run(rng, 100))
    np.testing.assert_allclose(detector.fitted.slope, 2.0, atol=0.01)  # the two normalizations, learned
    np.testing.assert_allclose(detector.fitted.intercept, 0.5, atol=0.05)
    follows = [detector.score(f) for f in _tracking_run(rng, 30)]
    lags = [detector.score(f) for f in _tracking_run(rng, 30, lag=1)]
    noisy = [detector.score(f) for f in _tracking_run(rng, 30, reading_noise=0.2)]
    assert np.max(follows) < 5.0 < min(np.min(lags), np.median(noisy))
    assert detector.score(_features(rng, previous_samples=None, shift=None)) == 0.0  # no command yet


def test_tracking_error_reads_the_executed_step_and_refuses_what_it_cannot_compare():
    samples = np.broadcast_to(np.arange(T, dtype=float)[:, None], (N, K, T, A))  # step t holds t
    np.testing.assert_array_equal(commanded_target(samples, action_start=1, shift=4), np.full(A, 4.0))
    with pytest.raises(ValueError, match="outside its chunk"):
        commanded_target(samples, action_start=1, shift=T)
    with pytest.raises(ValueError, match="M >= 3"):
        fit_tracking(np.zeros((2, A)), np.zeros((2, A)))
    fit = fit_tracking(np.arange(12.0).reshape(4, 3), np.arange(12.0).reshape(4, 3))  # exact: unit scale
    assert tracking_score(fit, np.zeros(3), np.zeros(3)) == pytest.approx(0.0)
    rng = np.random.default_rng(11)
    with pytest.raises(ValueError, match="not fitted"):
        TrackingErrorDetector().score(_features(rng))
    with pytest.raises(ValueError, match="the state each prediction was made from"):
        TrackingErrorDetector().fit([_features(rng, state=None)] * 3)
    with pytest.raises(ValueError, match="share one layout"):
        TrackingErrorDetector().fit([_features(rng, state=np.zeros(A + 1))] * 3)
    with pytest.raises(ValueError, match="consecutive predictions"):
        TrackingErrorDetector().fit([_features(rng, previous_samples=None, shift=None)] * 3)


def test_prediction_features_read_the_last_observation_steps_state_from_the_embedding():
    # Two observation steps of (state 2, image 3): LeRobot's conditioning [s0, img0, s1, img1] per member.
    embedding = np.tile(np.array([1.0, 2.0, 9.0, 9.0, 9.0, 3.0, 4.0, 8.0, 8.0, 8.0]), (N, 1))
    captured = {
        "episode": np.array([0, 0]),
        "step": np.array([0, 4]),
        "samples": np.zeros((2, N, K, T, A)),
        "embedding": np.stack([embedding, embedding]),
        "single": np.zeros((2, 6, T, A)),
    }
    first, second = prediction_features(captured, action_start=1, state_dim=2)
    np.testing.assert_array_equal(second.state, [3.0, 4.0])
    assert first.previous_samples is None and second.shift == 4
    assert prediction_features(captured, action_start=1)[0].state is None


def test_every_detector_follows_the_interface_and_reports_its_cost():
    rng = np.random.default_rng(8)
    nominal = [_features(rng) for _ in range(30)]
    for name in DETECTOR_NAMES:
        detector = make_detector(name)
        assert isinstance(detector, Detector) and detector.name == name
        scores, seconds = timed_scores(detector.fit(nominal), nominal[:5])
        assert scores.shape == (5,) and np.all(np.isfinite(scores)) and seconds > 0
    with pytest.raises(ValueError, match="Unknown detector 'x'"):
        make_detector("x")


def test_failure_prediction_balanced_accuracy():
    # Failures at their last step 9; successes None. An alarm after the failure does not predict it.
    first = [3, None, 12, None, 4, None]
    fail = [9, 9, 9, None, None, None]
    assert failure_prediction_balanced_accuracy(first, fail) == pytest.approx(0.5 * (1 / 3 + 2 / 3))
    assert failure_prediction_balanced_accuracy([0, 0], [5, None]) == 0.5  # always alarming
    assert failure_prediction_balanced_accuracy([None, None], [5, None]) == 0.5  # never alarming
    assert failure_prediction_balanced_accuracy([1, None], [5, None]) == 1.0
    assert math.isnan(failure_prediction_balanced_accuracy([1], [5]))  # no success to stay away from
    with pytest.raises(ValueError, match="one first alarm per episode"):
        failure_prediction_balanced_accuracy([1], [5, None])


def test_conformal_threshold_is_the_calibration_per_episode_threshold():
    rng = np.random.default_rng(9)
    scores = rng.lognormal(size=400)
    ids = np.repeat(np.arange(40), 10)
    maxima = np.array([scores[ids == e].max() for e in range(40)])
    cal = fit_calibration(scores, model="lognormal", alpha=0.05, mode="per_episode", episode_ids=ids)
    assert conformal_episode_threshold(maxima, 0.05) == cal.threshold
    with pytest.raises(ValueError, match="at least 19"):
        conformal_episode_threshold(maxima[:10], 0.05)


def test_hold_scores_keeps_the_latest_prediction():
    np.testing.assert_array_equal(hold_scores(np.array([0, 3]), np.array([1.0, 2.0]), 5), [1, 1, 1, 2, 2])
    with pytest.raises(ValueError, match="first control step"):
        hold_scores(np.array([1]), np.array([1.0]), 3)


@pytest.mark.parametrize("batched", [True, False])
def test_feature_capture_leaves_the_actions_bit_identical(batched):
    import torch
    from lerobot_policy_ensemble_diffusion.modeling_ensemble_diffusion import EnsembleDiffusionPolicy
    from policy_builders import tiny_config

    torch.manual_seed(0)
    policy = EnsembleDiffusionPolicy(tiny_config(batched_inference=batched)).eval()
    state_dim = policy.config.robot_state_feature.shape[0]
    gen = torch.Generator().manual_seed(1)
    obs = [
        {
            "observation.state": torch.randn(2, state_dim, generator=gen),
            **{k: torch.rand(2, *f.shape, generator=gen) for k, f in policy.config.image_features.items()},
        }
        for _ in range(6)
    ]

    def run(capture: bool):
        (policy.enable_feature_capture(4, seed=3) if capture else policy.disable_feature_capture())
        policy.reset()
        torch.manual_seed(7)
        actions = torch.stack([policy.select_action(o) for o in obs])
        return actions, torch.rand(1)  # and the global random state after the rollout

    plain, plain_rng = run(False)
    assert policy.last_features is None
    captured, captured_rng = run(True)
    torch.testing.assert_close(captured, plain, rtol=0, atol=0)
    torch.testing.assert_close(captured_rng, plain_rng, rtol=0, atol=0)
    f = policy.last_features
    assert f["embedding"].shape[:2] == (2, policy.config.n_members)
    assert f["single_member_samples"].shape == (2, 4, policy.config.horizon, 10)
    assert torch.isfinite(f["single_member_samples"]).all()
