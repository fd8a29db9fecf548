"""Pure metrics of the experiments: Wilson interval, paired change, AUROC, detection delay, alarm rates."""

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


def test_paired_change_counts_the_pairs_and_tests_them_exactly():
    before = [True] * 5 + [False] * 45
    after = [True] * 5 + [True] * 12 + [False] * 33
    r = metrics.paired_change(before, after)
    assert (r["improved"], r["worsened"], r["episodes"]) == (12, 0, 50)
    assert r["before"] == pytest.approx(0.10) and r["after"] == pytest.approx(0.34)
    assert r["change"] == pytest.approx(0.24)
    assert r["p_value"] == pytest.approx(2 * 0.5**12)  # McNemar exact: 12 of 12 discordant pairs one way
    lo, hi = r["interval"]
    assert 0 < lo < 0.24 < hi < 1
    # Swapping the runs mirrors everything.
    back = metrics.paired_change(after, before)
    assert back["change"] == pytest.approx(-0.24) and back["p_value"] == r["p_value"]
    assert back["interval"] == pytest.approx((-hi, -lo))
    same = metrics.paired_change(before, before)
    assert same["change"] == 0 and same["p_value"] == 1.0 and same["interval"][0] < 0 < same["interval"][1]
    assert math.isnan(metrics.paired_change([], [])["change"])
    with pytest.raises(ValueError, match="as many episodes"):
        metrics.paired_change([True], [True, False])


def test_paired_change_interval_covers_the_true_change():
    rng = np.random.default_rng(0)
    # Joint outcomes (both succeed, improved, worsened, neither) of 50 paired episodes.
    for probs in [(0.3, 0.2, 0.05, 0.45), (0.45, 0.1, 0.1, 0.35), (0.0, 0.3, 0.0, 0.7)]:
        covered = 0
        for _ in range(1000):
            kind = rng.choice(4, size=50, p=probs)
            r = metrics.paired_change(np.isin(kind, (0, 2)), np.isin(kind, (0, 1)))
            covered += r["interval"][0] <= probs[1] - probs[2] <= r["interval"][1]
        assert 0.93 <= covered / 1000 <= 0.995


def test_auroc_matches_the_pairwise_definition():
    rng = np.random.default_rng(0)
    neg, pos = rng.normal(0, 1, 50), rng.normal(1, 1, 40)
    pairs = np.mean([(p > n) + 0.5 * (p == n) for p in pos for n in neg])
    assert metrics.auroc(neg, pos) == pytest.approx(pairs)
    assert metrics.auroc([0, 1], [2, 3]) == 1.0 and metrics.auroc([2, 3], [0, 1]) == 0.0
    assert metrics.auroc([1, 1], [1]) == 0.5
    assert math.isnan(metrics.auroc([], [1.0]))


def test_auroc_interval_delong_by_hand_and_its_coverage():
    # Wins of positives 1.5 and 3 over negatives 0, 1, 2: rows [1, 1, 0], [1, 1, 1]; area 5/6; the
    # variances of the row and column means over their counts add up to 1/36 + 1/36.
    low, high = metrics.auroc_interval([0, 1, 2], [1.5, 3])
    half = 1.959963984540054 * math.sqrt(1 / 18)
    assert low == pytest.approx(5 / 6 - half) and high == 1.0
    assert metrics.auroc_interval([0, 1], [2, 3]) == (1.0, 1.0)  # separated: no spread left
    assert all(math.isnan(x) for x in metrics.auroc_interval([0.0], [1.0, 2.0]))
    # Normal scores one standard deviation apart: true AUROC Phi(1 / sqrt 2); about 95% of the
    # intervals of 300 seeded draws of 40 and 40 hold it.
    true_area = 0.5 * (1 + math.erf(0.5))
    rng = np.random.default_rng(0)
    covered = []
    for _ in range(300):
        neg, pos = rng.normal(0, 1, 40), rng.normal(1, 1, 40)
        low, high = metrics.auroc_interval(neg, pos)
        assert 0.0 <= low <= metrics.auroc(neg, pos) <= high <= 1.0
        covered.append(low <= true_area <= high)
    assert 0.90 <= np.mean(covered) <= 0.99


def test_auroc_over_common_steps_ignores_steps_only_one_episode_reached():
    nominal = [[0.1, 0.2, 0.1], [0.1, 0.3]]  # nominal episodes end early, at success
    # A perturbed run as quiet as nominal while both last, loud only after they have ended.
    late = [[0.1, 0.1, 0.1, 0.1, 9.0]]
    assert metrics.auroc([metrics.episode_score(n) for n in nominal], [9.0]) == 1.0
    assert metrics.auroc_over_common_steps(nominal, late) == 0.0
    # One loud while both last wins every pair; a tie counts a half.
    assert metrics.auroc_over_common_steps(nominal, [[0.1, 5.0, 0.0, 0.0]]) == 1.0
    assert metrics.auroc_over_common_steps([[0.2, 0.3]], [[0.2]]) == 0.5
    # The pairwise definition on random runs of random lengths, NaN scores skipped.
    rng = np.random.default_rng(0)
    neg = [rng.normal(0, 1, rng.integers(3, 30)) for _ in range(20)]
    pos = [rng.normal(0.5, 1, rng.integers(3, 30)) for _ in range(15)]
    pos[0][0] = np.nan
    expected = []
    for p in pos:
        for n in neg:
            k = min(len(p), len(n))
            a, b = np.nanmax(p[:k]), np.nanmax(n[:k])
            expected.append((a > b) + 0.5 * (a == b))
    assert metrics.auroc_over_common_steps(neg, pos) == pytest.approx(np.mean(expected))
    assert math.isnan(metrics.auroc_over_common_steps([], [[1.0]]))
    # A pair NaN over all its common steps, or ending before the perturbation began, is skipped.
    assert metrics.auroc_over_common_steps([[np.nan], [0.2, 0.2, 0.2]], [[np.nan, 0.4, 0.1]]) == 1.0
    assert metrics.auroc_over_common_steps([[0.3], [0.1, 0.1, 0.1]], [[0.2, 0.2, 0.2]], onsets=[1]) == 1.0
    assert math.isnan(metrics.auroc_over_common_steps([[0.3]], [[0.2, 0.2]], onsets=[1]))
    with pytest.raises(ValueError, match="one onset per positive"):
        metrics.auroc_over_common_steps([[0.3]], [[0.2]], onsets=[])


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
    assert rates["episodes"] == 3 and rates["alarmed_episodes"] == 1


def test_insertion_accuracy_counts_tolerances_and_missed_crossings():
    inf = math.inf
    result = metrics.insertion_accuracy([0.001, 0.003, 0.0015, inf], [0.001, 0.001, 0.004, inf], 0.002, 0.002)
    assert result["episodes"] == 4 and result["never_entered"] == 1 and result["never_emerged"] == 1
    assert result["entry_within_tolerance"] == 0.5 and result["exit_within_tolerance"] == 0.5
    assert result["both_within_tolerance"] == 0.25
    assert result["entry_error_mm"]["n"] == 3 and result["entry_error_mm"]["median"] == pytest.approx(1.5)
    with pytest.raises(ValueError, match="one entry and one exit error per episode"):
        metrics.insertion_accuracy([0.001], [], 0.002, 0.002)


def test_episode_score_ignores_nan_and_starts_where_asked():
    assert metrics.episode_score([math.nan, 1.0, 3.0, 2.0]) == 3.0
    assert metrics.episode_score([5.0, 1.0], start=1) == 1.0
    assert math.isnan(metrics.episode_score([math.nan]))


def test_uncertainty_figure_is_written_and_not_blank(tmp_path):
    from PIL import Image

    from lerobot_suture.experiments.plots import OOD_COLOUR, plot_uncertainty

    rng = np.random.default_rng(0)
    runs = [np.r_[rng.uniform(0.1, 0.2, 20), rng.uniform(0.5, 0.9, 30)] for _ in range(3)]
    nominal = [rng.uniform(0.1, 0.2, 50) for _ in range(2)]
    path = plot_uncertainty(
        runs, 0.3, tmp_path / "exp.png", "test", onset_steps=[20, 20, 20], nominal_runs=nominal
    )
    image = np.asarray(Image.open(path).convert("RGB"), dtype=float)
    assert image.std() > 10
    # The O.O.D. background (red) appears where the maximum crosses the threshold.
    red = np.array([int(OOD_COLOUR[i : i + 2], 16) for i in (1, 3, 5)], dtype=float)
    assert (np.abs(image - red).sum(axis=-1) < 6).any()


def test_share_of_maxima_at_end_counts_episodes_peaking_in_their_last_steps():
    late = list(range(20))  # max at the last step
    early = [5.0] + [0.0] * 19
    short = [0.0, 1.0]  # shorter than the window: its max is in it
    unscored = [math.nan] * 5
    assert metrics.share_of_maxima_at_end([late, early, short, unscored], end_steps=8) == pytest.approx(2 / 3)
    assert metrics.share_of_maxima_at_end([[math.nan, 3.0, math.nan, 1.0]], end_steps=2) == 0.0
    assert math.isnan(metrics.share_of_maxima_at_end([], end_steps=8))
    with pytest.raises(ValueError, match="`end_steps` must be >= 1"):
        metrics.share_of_maxima_at_end([late], end_steps=0)


def test_every_uncertainty_score_has_an_axis_label():
    from lerobot_policy_ensemble_diffusion.configuration_ensemble_diffusion import SCORE_CHOICES

    from lerobot_suture.experiments.plots import SCORE_LABELS

    assert set(SCORE_LABELS) == set(SCORE_CHOICES["uncertainty_score"])
