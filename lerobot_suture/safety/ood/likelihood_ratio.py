"""The one-sided likelihood-ratio test of the O.O.D. gate, and its false-alarm rates on I.D. scores.

Let x = g(score) (see :mod:`lerobot_suture.safety.ood.calibration`). Under H0 (I.D.) x ~ N(m, (h s)^2).
Only HIGH uncertainty is O.O.D., so the alternative is a shift upwards, H1: x ~ N(m + delta, (h s)^2)
with delta > 0. The log likelihood ratio is

    log [f1(x) / f0(x)] = delta * (2 (x - m) - delta) / (2 h^2 s^2),

which increases monotonically in x for every delta > 0. By the Neyman-Pearson lemma the most powerful
level-alpha test rejects H0 for x > c with P0(x > c) = alpha, i.e.

    c = m + z_{1-alpha} * h * s,        z_{1-alpha} = Phi^{-1}(1 - alpha),

and since c does not depend on delta the test is uniformly most powerful against the whole one-sided
alternative. Equivalently, the generalised LRT with H1: mean >= m has the statistic

    Lambda = log sup_{mu >= m} f(x | mu) / f(x | m) = max(z, 0)^2 / 2,        z = (x - m) / (h s),

and rejects for Lambda > z_{1-alpha}^2 / 2, i.e. for z > z_{1-alpha} (alpha < 0.5). Because g is
increasing, the rule is ``score > threshold`` with ``threshold = g^{-1}(c)``. That comparison is what this
module evaluates (exact at the threshold); :func:`log_likelihood_ratio` also returns Lambda for logging.
"""

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from lerobot_suture.safety.ood.calibration import (
    CalibrationModel,
    OODCalibration,
    episode_labels,
    score_transform,
)

__all__ = [
    "FalseAlarmRates",
    "LikelihoodRatio",
    "false_alarm_rates",
    "likelihood_ratio_test",
    "log_likelihood_ratio",
    "standardized_score",
]


def standardized_score(score: ArrayLike, calibration: OODCalibration) -> np.ndarray | float:
    """z = (g(score) - mean) / (h * std): the score in units of the widened I.D. spread.

    Args:
        score: Score(s), any shape ``(...)``. In ``per_episode`` mode pass the running maximum.
        calibration: The fitted calibration.

    Returns:
        z with the shape of ``score`` (a float for a scalar input). For ``lognormal``, score <= 0 gives
        -inf; NaN stays NaN.
    """
    x = score_transform(np.asarray(score, dtype=np.float64), CalibrationModel(calibration.model))
    z = (x - calibration.mean) / (calibration.h * calibration.std)
    return float(z) if np.ndim(z) == 0 else z


def likelihood_ratio_test(score: ArrayLike, calibration: OODCalibration) -> np.ndarray | bool:
    """One-sided likelihood-ratio test of M_ID against an upward shift: True means O.O.D.

    Evaluated as ``score > calibration.threshold`` (exact at the threshold: a score equal to it is I.D.),
    which is equivalent to the LRT statistic exceeding its critical value (module docstring). A NaN score
    (a broken ensemble prediction) is O.O.D.: the gate fails safe.

    Args:
        score: Score(s), any shape ``(...)``; in ``per_episode`` mode pass the running maximum of the
            episode's scores (see :class:`OODGate`).
        calibration: The fitted calibration.

    Returns:
        Decision(s) with the shape of ``score``: a Python bool for a scalar input, else a bool array.
    """
    score = np.asarray(score, dtype=np.float64)
    decision = (score > calibration.threshold) | np.isnan(score)
    return bool(decision) if decision.ndim == 0 else decision


class LikelihoodRatio(NamedTuple):
    """Result of :func:`log_likelihood_ratio`; fields have the shape of the score (floats for scalars)."""

    log_lr: np.ndarray | float
    """One-sided generalised log likelihood ratio, max(z, 0)^2 / 2, >= 0 (NaN for a NaN score)."""
    critical_value: float
    """Rejection level of ``log_lr``: critical_value(z)^2 / 2."""
    decision: np.ndarray | bool
    """True = O.O.D. (same as :func:`likelihood_ratio_test`)."""


def log_likelihood_ratio(score: ArrayLike, calibration: OODCalibration) -> LikelihoodRatio:
    """The one-sided generalised LRT statistic with its critical value and decision.

    Lambda = log sup_{mu >= mean} f(x | mu) / f(x | mean) = max(z, 0)^2 / 2 with z from
    :func:`standardized_score`; the test rejects for Lambda > critical_value^2 / 2, i.e. z >
    critical_value. The decision is computed as in :func:`likelihood_ratio_test` (score space, exact).

    Args:
        score: Score(s), any shape ``(...)`` (the running maximum in ``per_episode`` mode).
        calibration: The fitted calibration.

    Returns:
        ``LikelihoodRatio(log_lr, critical_value, decision)``; it unpacks like a tuple.
    """
    z = np.asarray(standardized_score(score, calibration))
    log_lr = 0.5 * np.square(np.maximum(z, 0.0))  # NaN propagates through np.maximum.
    log_lr = float(log_lr) if log_lr.ndim == 0 else log_lr
    critical = 0.5 * calibration.critical_value**2
    return LikelihoodRatio(log_lr, critical, likelihood_ratio_test(score, calibration))


@dataclass(frozen=True)
class FalseAlarmRates:
    """False-alarm rates of a calibration measured on I.D. scores.

    Args:
        per_step: Fraction of scores above the threshold.
        per_episode: Fraction of episodes whose maximum score is above the threshold (a latched gate
            releases control on exactly these), or None without episode labels.
        n_steps: Number of scores.
        n_episodes: Number of episodes, or None.
    """

    per_step: float
    per_episode: float | None
    n_steps: int
    n_episodes: int | None


def false_alarm_rates(
    scores: ArrayLike, calibration: OODCalibration, episode_ids: ArrayLike | None = None
) -> FalseAlarmRates:
    """Measure how often a calibration flags held-out I.D. scores.

    Args:
        scores: Held-out I.D. per-step scores, shape ``(N,)``.
        calibration: The calibration to check.
        episode_ids: Episode label of each score, shape ``(N,)``, for the per-episode rate.

    Returns:
        The per-step and per-episode false-alarm rates; compare the one matching ``calibration.mode``
        with ``calibration.alpha``.
    """
    scores = np.asarray(scores, dtype=np.float64)
    if scores.ndim != 1 or scores.size == 0:
        raise ValueError(f"`scores` must have shape (N,) with N >= 1. Got shape {scores.shape}.")
    alarms = np.asarray(likelihood_ratio_test(scores, calibration))  # (N,)
    per_episode = n_episodes = None
    if episode_ids is not None:
        labels, n_episodes = episode_labels(episode_ids, scores)
        episode_alarm = np.zeros(n_episodes, dtype=bool)
        np.logical_or.at(episode_alarm, labels, alarms)
        per_episode = float(np.mean(episode_alarm))
    return FalseAlarmRates(float(np.mean(alarms)), per_episode, int(scores.size), n_episodes)
