"""Pure metrics of the experiments: Wilson interval, AUROC, detection delay, alarm rates."""

import math

import numpy as np
import pytest

from lerobot_suture.experiments import metrics


def test_wilson_interval_known_values():
    low, high = metrics.wilson_interval(90, 100)
    assert low == pytest.approx(0.8256, abs=1e-3) and high == pytest.approx(0.9448, abs=1e-3)
    assert metrics.wilson_interval(0, 10)[0] == 0.0
    assert metrics.wilson_interval(10, 10)[1] == pytest.approx(1.0)
    assert all(math.isnan(x) for x in metrics.wilson_interval(0, 0))


def test_auroc_matches_the_pairwise_definition():
    rng = np.random.default_rng(0)
    neg, pos = rng.normal(0, 1, 50), rng.normal(1, 1, 40)
    pairs = np.mean([(p > n) + 0.5 * (p == n) for p in pos for n in neg])
    assert metrics.auroc(neg, pos) == pytest.approx(pairs)
    assert metrics.auroc([0, 1], [2, 3]) == 1.0 and metrics.auroc([2, 3], [0, 1]) == 0.0
    assert metrics.auroc([1, 1], [1]) == 0.5
    assert math.isnan(metrics.auroc([], [1.0]))


def test_detection_delay_counts_from_onset_to_the_first_alarm_at_or_after_it():
    alarms = [True, False, False, False, True, True]  # an early false alarm does not count
    assert metrics.first_alarm_after(alarms, 2) == 4
    assert metrics.detection_delays([(alarms, 2), ([False] * 4, 1), (alarms, None)]) == [2]
    summary = metrics.summarize([2, 4, 6])
    assert summary["median"] == 4 and summary["n"] == 3
    assert metrics.summarize([])["median"] is None


def test_alarm_rates_per_step_and_per_episode():
    rates = metrics.alarm_rates([[False, True], [False, False], [False, False]])
    assert rates["per_step"] == pytest.approx(1 / 6) and rates["per_episode"] == pytest.approx(1 / 3)


def test_episode_score_ignores_nan_and_starts_where_asked():
    assert metrics.episode_score([math.nan, 1.0, 3.0, 2.0]) == 3.0
    assert metrics.episode_score([5.0, 1.0], start=1) == 1.0
    assert math.isnan(metrics.episode_score([math.nan]))
