"""Tests of the O.O.D. gate core: scores, calibration, the one-sided test, the gate and its file."""

import dataclasses
import json
import math

import numpy as np
import pytest
from scipy import stats

from lerobot_suture.safety.ood.calibration import (
    CALIBRATION_FORMAT_VERSION,
    MIN_CALIBRATION_SAMPLES,
    OODCalibration,
    fit_calibration,
    min_calibration_episodes,
)
from lerobot_suture.safety.ood.calibration_file import (
    CALIBRATION_FILENAME,
    CalibrationNotFoundError,
    load_calibration,
    save_calibration,
)
from lerobot_suture.safety.ood.gate import OODGate
from lerobot_suture.safety.ood.likelihood_ratio import (
    false_alarm_rates,
    likelihood_ratio_test,
    log_likelihood_ratio,
    standardized_score,
)
from lerobot_suture.safety.ood.score import (
    ScoreName,
    compute_score,
    get_score_function,
    score_logdet,
    score_max_abs_cov,
    score_trace,
)

ALPHA = 0.05
N_SIGMA = 4.0  # Binomial tolerance of the false-alarm tests.


def _ensemble_covariances(rng: np.random.Generator, batch: int, horizon: int, action_dim: int, members: int):
    """Sample covariances of `members` random action sequences, shape (batch, horizon, A, A)."""
    actions = rng.normal(size=(batch, members, horizon, action_dim)) * rng.uniform(
        0.1, 2.0, size=(batch, 1, 1, 1)
    )
    centred = actions - actions.mean(axis=1, keepdims=True)  # (B, N, T, A)
    return np.einsum("bnti,bntj->btij", centred, centred) / (members - 1)  # (B, T, A, A)


def _ar1_lognormal_episodes(rng: np.random.Generator, n_episodes: int, length: int, rho: float = 0.8):
    """I.D. per-step scores of `n_episodes` episodes: log-normal with AR(1) correlation in time.

    Returns:
        scores of shape (n_episodes * length,) and episode ids of the same shape.
    """
    noise = rng.normal(size=(n_episodes, length))
    u = np.empty_like(noise)
    u[:, 0] = noise[:, 0]
    for t in range(1, length):
        u[:, t] = rho * u[:, t - 1] + math.sqrt(1.0 - rho**2) * noise[:, t]  # stationary N(0, 1)
    scores = np.exp(-3.0 + 0.5 * u)  # (E, T)
    ids = np.repeat(np.arange(n_episodes), length)
    return scores.reshape(-1), ids


def _binomial_tolerance(p: float, n: int) -> float:
    return N_SIGMA * math.sqrt(p * (1.0 - p) / n)


# Scores.


def test_scores_match_numpy_on_known_covariances():
    rng = np.random.default_rng(0)
    cov = _ensemble_covariances(rng, batch=6, horizon=8, action_dim=10, members=5)  # (6, 8, 10, 10)
    eps = 1e-6
    expected_max_abs = [max(np.abs(c).max() for c in steps) for steps in cov]
    expected_trace = [max(np.trace(c) for c in steps) for steps in cov]
    expected_logdet = [max(np.log(np.linalg.det(c + eps * np.eye(10))) for c in steps) for steps in cov]
    np.testing.assert_allclose(score_max_abs_cov(cov), expected_max_abs, rtol=0, atol=0)
    np.testing.assert_allclose(score_trace(cov), expected_trace, rtol=1e-12)
    np.testing.assert_allclose(score_logdet(cov, eps=eps), expected_logdet, rtol=1e-9)


def test_scores_on_hand_made_covariance():
    cov = np.zeros((2, 3, 3))  # (T, A, A)
    cov[0] = np.diag([1.0, 2.0, 3.0])
    cov[1] = [[1.0, -4.0, 0.0], [-4.0, 17.0, 0.0], [0.0, 0.0, 0.5]]
    assert score_max_abs_cov(cov) == 17.0  # the negative off-diagonal counts by its magnitude
    assert score_trace(cov) == 18.5
    assert score_logdet(cov, eps=1e-12) == pytest.approx(math.log(max(6.0, 0.5 * (17.0 - 16.0))), rel=1e-9)


def test_scores_batched_over_leading_axes():
    rng = np.random.default_rng(1)
    cov = _ensemble_covariances(rng, batch=12, horizon=4, action_dim=3, members=4).reshape(3, 4, 4, 3, 3)
    for name in ScoreName:
        batched = compute_score(cov, name)
        assert batched.shape == (3, 4)
        assert np.allclose(batched[2, 1], compute_score(cov[2, 1], name))
        assert np.ndim(compute_score(cov[0, 0], name)) == 0


def test_score_registry_lookup():
    assert get_score_function("max_abs_cov") is score_max_abs_cov
    assert get_score_function(ScoreName.TRACE) is score_trace
    assert get_score_function("logdet") is score_logdet
    with pytest.raises(ValueError, match="'max_abs_cov', 'trace', 'logdet'"):
        get_score_function("max_cov")


@pytest.mark.parametrize("shape", [(3, 3), (2, 3, 4), (0, 3, 3), (1, 0, 0)])
def test_scores_reject_bad_shapes(shape):
    with pytest.raises(ValueError, match="`cov`"):
        score_max_abs_cov(np.zeros(shape))


def test_nan_covariance_gives_nan_score():
    cov = np.full((2, 3, 3), np.nan)
    for name in ScoreName:
        assert np.isnan(compute_score(cov, name))


# Calibration and the test.


@pytest.mark.parametrize("model", ["normal", "lognormal"])
@pytest.mark.parametrize("h", [1.0, 2.5])
def test_per_prediction_threshold_formula(model, h):
    rng = np.random.default_rng(2)
    scores = rng.lognormal(mean=-2.0, sigma=0.4, size=500)
    cal = fit_calibration(scores, model=model, h=h, alpha=ALPHA)
    x = np.log(scores) if model == "lognormal" else scores
    cut = x.mean() + stats.norm.ppf(1 - ALPHA) * h * x.std(ddof=1)
    assert cal.threshold == pytest.approx(math.exp(cut) if model == "lognormal" else cut, rel=1e-12)
    assert cal.critical_value == pytest.approx(1.6448536269514722, rel=1e-12)
    assert (cal.model, cal.mode, cal.h, cal.alpha, cal.n_samples) == (model, "per_prediction", h, ALPHA, 500)
    assert cal.score_name == "max_abs_cov" and cal.space == "normalized"


@pytest.mark.parametrize("mode", ["per_prediction", "per_episode"])
def test_rejects_exactly_above_threshold(mode):
    rng = np.random.default_rng(3)
    scores, ids = _ar1_lognormal_episodes(rng, 40, 20)
    cal = fit_calibration(scores, model="lognormal", mode=mode, episode_ids=ids)
    thr = cal.threshold
    above = np.nextafter(thr, np.inf)
    below = np.nextafter(thr, -np.inf)
    assert likelihood_ratio_test(thr, cal) is False
    assert likelihood_ratio_test(below, cal) is False
    assert likelihood_ratio_test(above, cal) is True
    decisions = likelihood_ratio_test(np.array([[below, thr], [above, np.nan]]), cal)
    np.testing.assert_array_equal(decisions, [[False, False], [True, True]])  # NaN fails safe


def test_log_likelihood_ratio_agrees_with_decision():
    rng = np.random.default_rng(4)
    cal = fit_calibration(rng.normal(1.0, 0.2, size=1000), model="normal")
    probe = np.linspace(0.0, 2.0, 201)
    log_lr, critical, decision = log_likelihood_ratio(probe, cal)
    assert log_lr.shape == probe.shape and decision.shape == probe.shape
    assert np.all(log_lr >= 0)
    assert np.all(log_lr[probe <= cal.mean] == 0)  # one-sided: low uncertainty is never evidence of O.O.D.
    assert critical == pytest.approx(0.5 * cal.critical_value**2)
    away = np.abs(probe - cal.threshold) > 1e-9
    np.testing.assert_array_equal(decision[away], (log_lr > critical)[away])
    np.testing.assert_array_equal(decision, likelihood_ratio_test(probe, cal))
    z = standardized_score(probe, cal)
    np.testing.assert_allclose(log_lr, 0.5 * np.maximum(z, 0) ** 2)
    scalar = log_likelihood_ratio(float(probe[-1]), cal)
    assert isinstance(scalar.log_lr, float) and scalar.decision is True


@pytest.mark.parametrize("model", ["normal", "lognormal"])
def test_per_prediction_false_alarm_rate(model):
    rng = np.random.default_rng(5)
    n_cal, n_test = 20_000, 20_000
    draw = (
        (lambda n: rng.normal(0.1, 0.02, n)) if model == "normal" else (lambda n: rng.lognormal(-3, 0.5, n))
    )
    cal = fit_calibration(draw(n_cal), model=model, alpha=ALPHA)
    rates = false_alarm_rates(draw(n_test), cal)
    # Sampling noise of the test set plus that of the fitted threshold (delta method on mean + z std).
    z = stats.norm.ppf(1 - ALPHA)
    sd = math.sqrt(ALPHA * (1 - ALPHA) / n_test + stats.norm.pdf(z) ** 2 * (1 + z**2 / 2) / n_cal)
    assert abs(rates.per_step - ALPHA) < N_SIGMA * sd
    assert rates.per_episode is None and rates.n_steps == n_test


@pytest.mark.parametrize("model", ["normal", "lognormal"])
def test_per_episode_false_alarm_rate(model):
    rng = np.random.default_rng(6)
    n_episodes, length = 2000, 80
    cal_scores, cal_ids = _ar1_lognormal_episodes(rng, n_episodes, length)
    test_scores, test_ids = _ar1_lognormal_episodes(rng, n_episodes, length)
    cal = fit_calibration(cal_scores, model=model, alpha=ALPHA, mode="per_episode", episode_ids=cal_ids)
    assert cal.n_episodes == n_episodes and cal.mean_episode_length == length
    assert cal.quantile_rank == math.ceil((n_episodes + 1) * (1 - ALPHA))
    rates = false_alarm_rates(test_scores, cal, episode_ids=test_ids)
    # The realised rate of the calibrated threshold scatters like the test-set estimate (Beta, same n).
    tolerance = N_SIGMA * math.sqrt(2 * ALPHA * (1 - ALPHA) / n_episodes)
    assert abs(rates.per_episode - ALPHA) < tolerance
    # The paper's per-prediction calibration raises a false alarm on most of these I.D. episodes.
    per_prediction = fit_calibration(cal_scores, model=model, alpha=ALPHA)
    assert false_alarm_rates(test_scores, per_prediction, episode_ids=test_ids).per_episode > 0.5


def test_per_episode_threshold_is_order_statistic_and_h_widens():
    rng = np.random.default_rng(7)
    scores, ids = _ar1_lognormal_episodes(rng, 99, 30)
    maxima = scores.reshape(99, 30).max(axis=1)
    cal = fit_calibration(scores, model="lognormal", mode="per_episode", episode_ids=ids)
    assert cal.quantile_rank == 95  # ceil(100 * 0.95)
    assert cal.threshold == np.sort(maxima)[94]
    wide = fit_calibration(scores, model="lognormal", h=2.0, mode="per_episode", episode_ids=ids)
    assert wide.critical_value == cal.critical_value
    assert math.log(wide.threshold) == pytest.approx(cal.mean + 2.0 * cal.critical_value * cal.std)
    assert wide.threshold > cal.threshold


def test_min_calibration_episodes():
    assert min_calibration_episodes(0.05) == 19
    assert min_calibration_episodes(0.1) == 9
    scores, ids = _ar1_lognormal_episodes(np.random.default_rng(8), 19, 10)
    fit_calibration(scores, mode="per_episode", episode_ids=ids)  # exactly enough
    with pytest.raises(ValueError, match="at least 19 I.D. episodes"):
        fit_calibration(scores[:180], mode="per_episode", episode_ids=ids[:180])


_GOOD = np.random.default_rng(9).lognormal(-2.0, 0.3, size=50)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"scores": []}, "empty"),
        ({"scores": np.append(_GOOD, np.nan)}, "finite"),
        ({"scores": np.append(_GOOD, np.inf)}, "finite"),
        ({"scores": np.append(_GOOD, 0.0), "model": "lognormal"}, "> 0 for model 'lognormal'"),
        ({"scores": _GOOD.reshape(5, 10)}, r"shape \(N,\)"),
        ({"scores": _GOOD[: MIN_CALIBRATION_SAMPLES - 1]}, f"at least {MIN_CALIBRATION_SAMPLES} samples"),
        ({"scores": np.ones(50)}, "all equal"),
        ({"alpha": 0.0}, "`alpha` must be in"),
        ({"alpha": 1.5}, r"Got 1\.5\."),
        ({"alpha": 0.5}, "`alpha` must be in"),
        ({"alpha": float("nan")}, "`alpha` must be in"),
        ({"h": 0.0}, "`h` must be"),
        ({"h": -1.0}, "`h` must be"),
        ({"h": float("inf")}, "`h` must be"),
        ({"model": "gamma"}, "`model` must be one of 'normal', 'lognormal'"),
        ({"mode": "episode"}, "`mode` must be one of"),
        ({"space": "joint"}, "`space` must be one of"),
        ({"score_name": "var"}, "Valid names"),
        ({"score_settings": {"uncertainty_source": ["total"]}}, "`score_settings` must map"),
        ({"mode": "per_episode"}, "`episode_ids` is required"),
        ({"episode_ids": np.zeros(3)}, "`episode_ids` must have the shape"),
    ],
)
def test_fit_calibration_rejects_invalid_inputs(kwargs, match):
    kwargs = {"scores": _GOOD, **kwargs}
    with pytest.raises(ValueError, match=match):
        fit_calibration(**kwargs)


# The gate.


def test_gate_latches_and_holds_until_reset():
    rng = np.random.default_rng(10)
    cal = fit_calibration(rng.normal(1.0, 0.1, size=500))
    gate = OODGate(cal, enforce=True)
    low, high = cal.mean, cal.threshold + 1.0
    assert gate.threshold == cal.threshold
    assert gate.update(low) is False and not gate.released
    assert gate.update(high) is True and gate.released and gate.released_at == 1
    assert gate.update(low) is False  # the per-prediction decision follows the score ...
    assert gate.released and gate.released_at == 1  # ... but control stays released
    assert gate.last_score == low and gate.running_max == high and gate.n_updates == 3
    gate.reset()
    assert not gate.released and not gate.decision and gate.released_at is None and gate.n_updates == 0
    assert math.isnan(gate.last_score) and gate.running_max == -math.inf
    assert gate.update(low) is False and not gate.released


def test_per_episode_gate_tests_running_max():
    scores, ids = _ar1_lognormal_episodes(np.random.default_rng(11), 100, 40)
    cal = fit_calibration(scores, model="lognormal", mode="per_episode", episode_ids=ids)
    gate = OODGate(cal)
    gate.update(cal.threshold)  # at the threshold: I.D.
    assert not gate.decision
    gate.update(np.nextafter(cal.threshold, np.inf))
    gate.update(1e-6)  # a low score after a high one: the running max still exceeds
    assert gate.decision and gate.released and gate.released_at == 1
    assert gate.last_statistic == pytest.approx(standardized_score(gate.running_max, cal))


def test_gate_nan_score_fails_safe():
    cal = fit_calibration(np.random.default_rng(12).normal(1.0, 0.1, size=100))
    gate = OODGate(cal)
    assert gate.update(float("nan")) is True and gate.released
    assert gate.running_max == -math.inf


def test_gate_without_calibration():
    gate = OODGate()  # reporting only, e.g. while recording calibration rollouts
    assert gate.update(3.0) is False and gate.update(1.0) is False
    assert gate.running_max == 3.0 and gate.last_score == 1.0 and math.isnan(gate.threshold)
    with pytest.raises(ValueError, match="lerobot-suture calibrate --policy.path=DIR"):
        OODGate(None, enforce=True)


# Save / load.


@pytest.mark.parametrize("mode", ["per_prediction", "per_episode"])
def test_calibration_json_round_trip(tmp_path, mode):
    scores, ids = _ar1_lognormal_episodes(np.random.default_rng(13), 30, 25)
    settings = {
        "uncertainty_samples_per_member": 8,
        "uncertainty_source": "total",
        "num_inference_steps": None,
    }
    cal = fit_calibration(
        scores,
        model="lognormal",
        h=1.3,
        mode=mode,
        episode_ids=ids,
        score_name="trace",
        score_settings=settings,
    )
    path = save_calibration(cal, tmp_path / "pretrained_model")
    assert path == tmp_path / "pretrained_model" / CALIBRATION_FILENAME
    assert json.loads(path.read_text())["version"] == CALIBRATION_FORMAT_VERSION
    loaded = load_calibration(path.parent)
    assert loaded == cal
    for f in dataclasses.fields(cal):
        assert getattr(loaded, f.name) == getattr(cal, f.name), f.name  # exact, no rounding
    assert sorted(p.name for p in path.parent.iterdir()) == [CALIBRATION_FILENAME]  # no temp file left


def test_load_missing_calibration_says_how_to_calibrate(tmp_path):
    with pytest.raises(CalibrationNotFoundError, match="lerobot-suture calibrate --policy.path=DIR"):
        load_calibration(tmp_path)
    assert issubclass(CalibrationNotFoundError, FileNotFoundError)


def _write(tmp_path, data):
    text = data if isinstance(data, str) else json.dumps(data)
    (tmp_path / CALIBRATION_FILENAME).write_text(text)


@pytest.fixture
def saved_dict():
    cal = fit_calibration(np.random.default_rng(14).lognormal(-2, 0.3, 200), model="lognormal")
    return cal.to_dict()


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda d: "{not json", "not valid JSON"),
        (lambda d: [1, 2], "JSON object"),
        (lambda d: {k: v for k, v in d.items() if k != "threshold"}, "missing the key.*'threshold'"),
        (lambda d: {k: v for k, v in d.items() if k != "version"}, "`version`"),
        (lambda d: {**d, "version": 99}, "`version` must be 1"),
        (lambda d: {**d, "extra": 1}, r"unknown key\(s\) \['extra'\]"),
        (lambda d: {**d, "alpha": 1.5}, r"`alpha` must be in \(0, 0\.5\).*Got 1\.5\."),
        (lambda d: {**d, "std": -1.0}, "`std` must be > 0"),
        (lambda d: {**d, "mean": "high"}, "`mean` must be a finite number"),
        (lambda d: {**d, "model": "cauchy"}, "`model` must be one of"),
        (lambda d: {**d, "mode": "per_episode"}, "`n_episodes` is required"),
        (lambda d: {**d, "threshold": d["threshold"] * 1.01}, "`threshold`.*inconsistent"),
        (lambda d: {**d, "n_samples": 0}, "`n_samples` must be an integer >= 1"),
    ],
)
def test_load_malformed_calibration_names_the_problem(tmp_path, saved_dict, edit, match):
    _write(tmp_path, edit(saved_dict))
    with pytest.raises(ValueError, match=match):
        load_calibration(tmp_path)


def test_calibration_is_frozen_and_validated_on_construction():
    cal = fit_calibration(np.random.default_rng(15).normal(1.0, 0.1, size=100))
    assert isinstance(cal, OODCalibration)
    with pytest.raises(dataclasses.FrozenInstanceError):
        cal.alpha = 0.1  # type: ignore[misc]
    with pytest.raises(ValueError, match=r"`alpha` must be in \(0, 0\.5\)"):
        dataclasses.replace(cal, alpha=0.7)
    with pytest.raises(ValueError, match="`quantile_rank` is only used in mode 'per_episode'"):
        dataclasses.replace(cal, quantile_rank=3)
