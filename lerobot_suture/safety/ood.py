"""Out-of-distribution (O.O.D.) gate: uncertainty scores, calibration and a one-sided likelihood-ratio test.

The paper's first safety layer. An ensemble of N diffusion policies predicts N action sequences; per
predicted step t the ensemble gives a covariance Sigma_t (A x A). A scalar uncertainty score summarises
the prediction, and a test against a model of in-distribution (I.D.) scores decides whether the current
state is O.O.D., in which case control is released to the surgeon.

Scores (shape ``(..., T, A, A)`` -> ``(...)``, batched over leading axes):

    max_abs_cov   sigma_hat = max_t max_{i,j} |Sigma_t[i, j]|          (the paper's score)
    trace         max_t tr(Sigma_t)                                    (total variance)
    logdet        max_t log det(Sigma_t + eps I)                       (log generalised variance)

Scores are unit-free when the covariance is computed in the policy's normalized action space (the
default, recorded as ``space="normalized"`` in the calibration).

I.D. model and test (paper: M_ID = Normal(mean, h * std), LRT at significance alpha). Let x = g(score),
with g the identity (``model="normal"``) or the natural log (``model="lognormal"``, since the score is
positive and right-skewed). Under H0 (I.D.) x ~ N(m, (h s)^2), with m, s the sample mean and standard
deviation of g(I.D. scores) and h > 0 a widening factor. Only HIGH uncertainty is O.O.D., so the
alternative is a shift upwards, H1: x ~ N(m + delta, (h s)^2) with delta > 0. The log likelihood ratio is

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

Two calibration modes:

* ``per_prediction`` (the paper's): every prediction is tested at level alpha. On an I.D. episode of T
  predictions the chance of at least one false alarm is up to 1 - (1 - alpha)^T (0.98 for T = 80 at
  alpha = 0.05 with independent scores), so a latched gate stops most long I.D. episodes.
* ``per_episode``: the test is applied to the running maximum of the scores within an episode, with a
  threshold chosen so that the per-episode false-alarm rate on I.D. episodes is about alpha; see
  :func:`fit_calibration` for the finite-sample quantile used and why.

A gate that latches (:class:`OODGate`) releases control on an episode iff the episode's maximum score
exceeds the threshold in both modes, so the modes differ only in how the threshold is chosen.
"""

import json
import math
import numbers
import os
import tempfile
from collections.abc import Callable
from dataclasses import MISSING, asdict, dataclass, field, fields
from enum import StrEnum
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats

__all__ = [
    "CALIBRATION_FILENAME",
    "CALIBRATION_FORMAT_VERSION",
    "CalibrationMode",
    "CalibrationModel",
    "CalibrationNotFoundError",
    "FalseAlarmRates",
    "LikelihoodRatio",
    "MIN_CALIBRATION_SAMPLES",
    "OODCalibration",
    "OODGate",
    "ScoreName",
    "ScoreSpace",
    "compute_score",
    "false_alarm_rates",
    "fit_calibration",
    "get_score_function",
    "likelihood_ratio_test",
    "load_calibration",
    "log_likelihood_ratio",
    "min_calibration_episodes",
    "save_calibration",
    "score_logdet",
    "score_max_abs_cov",
    "score_trace",
    "standardized_score",
]

CALIBRATION_FILENAME = "ood_calibration.json"
"""Name of the calibration file inside a pretrained policy directory."""

CALIBRATION_FORMAT_VERSION = 1
"""Version of the calibration JSON format; bumped on any incompatible change."""

MIN_CALIBRATION_SAMPLES = 10
"""Fewest per-step I.D. scores accepted by :func:`fit_calibration` (a floor, not a recommendation)."""

LOGDET_EPS = 1e-6
"""Default diagonal regulariser for :func:`score_logdet`: N ensemble members give rank <= N - 1."""

_CALIBRATE_HINT = (
    "Calibrate the policy first with `lerobot-suture calibrate --policy.path=DIR` (DIR is the pretrained "
    "policy directory), or set `ood.enforce=false` to only report scores."
)


# Scores.


def _as_covariance(cov: ArrayLike) -> np.ndarray:
    """Return ``cov`` as a float64 array of shape ``(..., T, A, A)`` with T, A >= 1, or raise."""
    cov = np.asarray(cov, dtype=np.float64)
    if cov.ndim < 3 or cov.shape[-1] != cov.shape[-2]:
        raise ValueError(
            "`cov` must have shape (..., T, A, A): per predicted step t an A x A action covariance. "
            f"Got shape {cov.shape}."
        )
    if cov.shape[-3] == 0 or cov.shape[-1] == 0:
        raise ValueError(f"`cov` must have at least one predicted step and one action dim. Got {cov.shape}.")
    return cov


def score_max_abs_cov(cov: ArrayLike) -> np.ndarray:
    """The paper's score: sigma_hat = max over steps t and entries (i, j) of |Sigma_t[i, j]|.

    Args:
        cov: Ensemble action covariance per predicted step, shape ``(..., T, A, A)``.

    Returns:
        Score of shape ``(...)`` (a 0-d value for an unbatched ``(T, A, A)`` input), >= 0. NaN entries
        propagate to NaN, which the test treats as O.O.D.
    """
    cov = _as_covariance(cov)
    return np.max(np.abs(cov), axis=(-3, -2, -1))


def score_trace(cov: ArrayLike) -> np.ndarray:
    """Total variance: max over steps t of tr(Sigma_t).

    Args:
        cov: Ensemble action covariance per predicted step, shape ``(..., T, A, A)``.

    Returns:
        Score of shape ``(...)``, >= 0 for positive semi-definite ``cov``.
    """
    cov = _as_covariance(cov)
    return np.max(np.trace(cov, axis1=-2, axis2=-1), axis=-1)


def score_logdet(cov: ArrayLike, eps: float = LOGDET_EPS) -> np.ndarray:
    """Log generalised variance: max over steps t of log det(Sigma_t + eps I).

    With N ensemble members the sample covariance has rank <= N - 1, so for N <= A it is singular; the
    regulariser ``eps`` (in the units of ``cov``, i.e. squared normalized action units by default) keeps
    the log-determinant finite. The score can be negative, so calibrate it with ``model="normal"``.

    Args:
        cov: Ensemble action covariance per predicted step, shape ``(..., T, A, A)``, positive
            semi-definite.
        eps: Diagonal regulariser, > 0.

    Returns:
        Score of shape ``(...)``. NaN entries in ``cov`` give NaN.

    Raises:
        ValueError: If ``eps <= 0`` or a regularised covariance is not positive definite.
    """
    if not eps > 0:
        raise ValueError(f"`eps` must be > 0. Got {eps}.")
    cov = _as_covariance(cov)
    eye = np.eye(cov.shape[-1])
    with np.errstate(invalid="ignore"):
        sign, logabsdet = np.linalg.slogdet(cov + eps * eye)  # (..., T)
    finite = np.isfinite(logabsdet)
    if np.any(finite & (sign <= 0)):
        raise ValueError(
            f"`cov` + {eps} * I must be positive definite for `score_logdet`; got a non-positive "
            "determinant. Pass a covariance (positive semi-definite) or raise `eps`."
        )
    return np.max(logabsdet, axis=-1)


class ScoreName(StrEnum):
    """Names of the uncertainty scores, as written in configs and in the calibration file."""

    MAX_ABS_COV = "max_abs_cov"
    TRACE = "trace"
    LOGDET = "logdet"

    @classmethod
    def parse(cls, name: "str | ScoreName") -> "ScoreName":
        """Validated lookup: return the member for ``name`` or raise a ValueError listing the valid ones."""
        try:
            return cls(name)
        except ValueError:
            valid = ", ".join(repr(m.value) for m in cls)
            raise ValueError(f"Unknown OOD score name {name!r}. Valid names: {valid}.") from None


_SCORE_FUNCTIONS: dict[ScoreName, Callable[[ArrayLike], np.ndarray]] = {
    ScoreName.MAX_ABS_COV: score_max_abs_cov,
    ScoreName.TRACE: score_trace,
    ScoreName.LOGDET: score_logdet,
}


def get_score_function(name: str | ScoreName) -> Callable[[ArrayLike], np.ndarray]:
    """Return the score function registered under ``name`` (see :class:`ScoreName`).

    Raises:
        ValueError: If ``name`` is unknown; the message lists the valid names.
    """
    return _SCORE_FUNCTIONS[ScoreName.parse(name)]


def compute_score(cov: ArrayLike, name: str | ScoreName = ScoreName.MAX_ABS_COV) -> np.ndarray:
    """Compute the score ``name`` of ``cov``, shape ``(..., T, A, A)`` -> ``(...)``."""
    return get_score_function(name)(cov)


# Calibration.


class CalibrationModel(StrEnum):
    """Family of the I.D. score model: Normal on the score, or Normal on the log score."""

    NORMAL = "normal"
    LOGNORMAL = "lognormal"


class CalibrationMode(StrEnum):
    """What the threshold is applied to: each prediction's score, or the running maximum in an episode."""

    PER_PREDICTION = "per_prediction"
    PER_EPISODE = "per_episode"


class ScoreSpace(StrEnum):
    """Space in which the ensemble covariance (and so the score) was computed."""

    NORMALIZED = "normalized"
    UNNORMALIZED = "unnormalized"


def _parse_enum(enum_cls: type[StrEnum], value: Any, name: str) -> StrEnum:
    try:
        return enum_cls(value)
    except ValueError:
        valid = ", ".join(repr(m.value) for m in enum_cls)
        raise ValueError(f"`{name}` must be one of {valid}. Got {value!r}.") from None


def _check_alpha(alpha: Any) -> None:
    if isinstance(alpha, bool) or not isinstance(alpha, numbers.Real) or not 0.0 < alpha < 0.5:
        raise ValueError(
            f"`alpha` must be in (0, 0.5): a one-sided level-alpha test with alpha >= 0.5 would flag "
            f"scores below the I.D. mean. Got {alpha!r}."
        )


def _check_h(h: Any) -> None:
    if isinstance(h, bool) or not isinstance(h, numbers.Real) or not (math.isfinite(h) and h > 0):
        raise ValueError(f"`h` must be a finite number > 0 (1.0 is the fitted spread). Got {h!r}.")


def _check_score_settings(settings: Any) -> dict[str, Any]:
    """A copy of ``settings`` if it maps names to JSON scalars (what the calibration file can hold)."""
    if not isinstance(settings, dict) or not all(
        isinstance(key, str) and (value is None or isinstance(value, (str, int, float, bool)))
        for key, value in settings.items()
    ):
        raise ValueError(
            "`score_settings` must map setting names to plain values (str, int, float, bool or None). "
            f"Got {settings!r}."
        )
    return dict(settings)


def _transform(scores: np.ndarray, model: CalibrationModel) -> np.ndarray:
    """g(score): identity for ``normal``, natural log for ``lognormal`` (log 0 = -inf)."""
    if model is CalibrationModel.LOGNORMAL:
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.log(scores)
    return scores


def _inverse_transform(x: float, model: CalibrationModel) -> float:
    return math.exp(x) if model is CalibrationModel.LOGNORMAL else x


def default_model(score_name: str | ScoreName) -> str:
    """The I.D. model for a score: ``lognormal`` (positive, skewed scores), ``normal`` for ``logdet``,
    which can be negative."""
    name = ScoreName.parse(score_name)
    return (CalibrationModel.NORMAL if name == ScoreName.LOGDET else CalibrationModel.LOGNORMAL).value


def min_calibration_episodes(alpha: float) -> int:
    """Fewest I.D. episodes for a ``per_episode`` calibration at level ``alpha``.

    The threshold is the k-th smallest of n episode maxima with k = ceil((n + 1)(1 - alpha)), which
    exists only if k <= n, i.e. n >= (1 - alpha) / alpha (19 at alpha = 0.05).
    """
    _check_alpha(alpha)
    return max(2, math.ceil((1.0 - alpha) / alpha - 1e-9))


def _quantile_rank(n: int, alpha: float) -> int:
    """k = ceil((n + 1)(1 - alpha)), guarded against float round-up at exact integers."""
    return math.ceil((n + 1) * (1.0 - alpha) - 1e-9)


@dataclass(frozen=True)
class OODCalibration:
    """A fitted I.D. model of the uncertainty score and the threshold of the one-sided test.

    The decision is ``score > threshold`` (``per_prediction``) or ``running_max > threshold``
    (``per_episode``); ``critical_value`` is the same threshold as a standardized statistic
    z = (g(score) - mean) / (h * std). Build it with :func:`fit_calibration`; constructing it directly
    (as :func:`load_calibration` does) validates every field.

    Args:
        model: ``"normal"`` (g = identity) or ``"lognormal"`` (g = log).
        mean: Sample mean of g(I.D. per-step scores).
        std: Sample standard deviation (ddof = 1) of g(I.D. per-step scores), > 0.
        h: Widening factor of the I.D. model, M_ID = Normal(mean, h * std), > 0.
        alpha: Significance level of the one-sided test, in (0, 0.5).
        mode: ``"per_prediction"`` or ``"per_episode"``.
        threshold: Score above which the test says O.O.D., in score units; equals
            g^{-1}(mean + critical_value * h * std).
        critical_value: Threshold of the standardized statistic z; z_{1-alpha} in ``per_prediction``
            mode, > 0 in both modes.
        n_samples: Number of I.D. per-step scores used for ``mean`` and ``std``.
        score_name: Name of the score (see :class:`ScoreName`).
        space: ``"normalized"`` or ``"unnormalized"`` action space of the covariance.
        score_settings: The scorer's other settings that shape the score's distribution (e.g. the
            samples per member), name -> value, as the policy reported them at fit time; the policy
            refuses a calibration whose settings differ from its own. None: not recorded.
        n_episodes: Number of I.D. episodes (required for ``per_episode``, else optional).
        quantile_rank: ``per_episode`` only: rank k of the episode maximum used as threshold (at h = 1).
        mean_episode_length: ``per_episode`` only: mean number of scores per calibration episode; the
            per-episode false-alarm rate holds for episodes of about this length.
        version: Calibration format version, :data:`CALIBRATION_FORMAT_VERSION`.
    """

    model: str
    mean: float
    std: float
    h: float
    alpha: float
    mode: str
    threshold: float
    critical_value: float
    n_samples: int
    score_name: str = ScoreName.MAX_ABS_COV.value
    space: str = ScoreSpace.NORMALIZED.value
    score_settings: dict[str, Any] | None = None
    n_episodes: int | None = None
    quantile_rank: int | None = None
    mean_episode_length: float | None = None
    version: int = CALIBRATION_FORMAT_VERSION

    def __post_init__(self):
        if (
            isinstance(self.version, bool)
            or not isinstance(self.version, int)
            or self.version != CALIBRATION_FORMAT_VERSION
        ):
            raise ValueError(
                f"`version` must be {CALIBRATION_FORMAT_VERSION} (the calibration format this code reads). "
                f"Got {self.version!r}. Re-run `lerobot-suture calibrate --policy.path=DIR`."
            )
        # Store plain strings so equality, hashing and JSON do not depend on how a field was passed.
        object.__setattr__(self, "model", _parse_enum(CalibrationModel, self.model, "model").value)
        object.__setattr__(self, "mode", _parse_enum(CalibrationMode, self.mode, "mode").value)
        object.__setattr__(self, "space", _parse_enum(ScoreSpace, self.space, "space").value)
        object.__setattr__(self, "score_name", ScoreName.parse(self.score_name).value)
        if self.score_settings is not None:
            object.__setattr__(self, "score_settings", _check_score_settings(self.score_settings))
        for name in ("mean", "std", "threshold", "critical_value"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
                raise ValueError(f"`{name}` must be a finite number. Got {value!r}.")
            object.__setattr__(self, name, float(value))
        if not self.std > 0:
            raise ValueError(f"`std` must be > 0. Got {self.std}.")
        _check_h(self.h)
        _check_alpha(self.alpha)
        object.__setattr__(self, "h", float(self.h))
        object.__setattr__(self, "alpha", float(self.alpha))
        if not self.critical_value > 0:
            raise ValueError(
                f"`critical_value` must be > 0 (above the I.D. mean). Got {self.critical_value}."
            )
        if self.model == CalibrationModel.LOGNORMAL and not self.threshold > 0:
            raise ValueError(f"`threshold` must be > 0 for model 'lognormal'. Got {self.threshold}.")
        for name in ("n_samples", "n_episodes", "quantile_rank"):
            value = getattr(self, name)
            if value is None and name != "n_samples":
                continue
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"`{name}` must be an integer >= 1. Got {value!r}.")
        if self.mean_episode_length is not None and not (
            isinstance(self.mean_episode_length, numbers.Real) and self.mean_episode_length >= 1
        ):
            raise ValueError(
                f"`mean_episode_length` must be a number >= 1. Got {self.mean_episode_length!r}."
            )
        if self.mode == CalibrationMode.PER_EPISODE:
            for name in ("n_episodes", "quantile_rank", "mean_episode_length"):
                if getattr(self, name) is None:
                    raise ValueError(f"`{name}` is required for mode 'per_episode'. Got None.")
            if self.quantile_rank > self.n_episodes:
                raise ValueError(
                    f"`quantile_rank` must be <= `n_episodes` ({self.n_episodes}). Got {self.quantile_rank}."
                )
        elif self.quantile_rank is not None:
            raise ValueError(f"`quantile_rank` is only used in mode 'per_episode'. Got {self.quantile_rank}.")
        # `threshold` and (`mean`, `std`, `h`, `critical_value`) are two views of one number.
        model = CalibrationModel(self.model)
        expected = self.mean + self.critical_value * self.h * self.std
        actual = float(_transform(np.float64(self.threshold), model))
        tol = 1e-9 * (abs(self.mean) + self.h * self.std * (1.0 + abs(self.critical_value)))
        if not abs(actual - expected) <= tol:
            raise ValueError(
                f"`threshold` ({self.threshold!r}) is inconsistent with `mean` + `critical_value` * `h` * "
                f"`std` ({_inverse_transform(expected, model)!r} in score units). Re-run the calibration "
                "instead of editing the file."
            )

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready dictionary of all fields."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "OODCalibration":
        """Inverse of :meth:`to_dict`; raises a ValueError naming a missing, unknown or invalid key."""
        if not isinstance(data, dict):
            raise ValueError(f"An OOD calibration must be a JSON object. Got {type(data).__name__}.")
        version = data.get("version")
        if version is None or isinstance(version, bool) or version != CALIBRATION_FORMAT_VERSION:
            raise ValueError(
                f"`version` must be {CALIBRATION_FORMAT_VERSION} (the calibration format this code reads). "
                f"Got {version!r}. Re-run `lerobot-suture calibrate --policy.path=DIR`."
            )
        names = [f.name for f in fields(cls)]
        missing = [f.name for f in fields(cls) if f.default is MISSING and f.name not in data]
        if missing:
            raise ValueError(f"OOD calibration is missing the key(s) {', '.join(map(repr, missing))}.")
        unknown = sorted(set(data) - set(names))
        if unknown:
            raise ValueError(f"OOD calibration has unknown key(s) {unknown}. Valid keys: {names}.")
        return cls(**data)


def fit_calibration(
    scores: ArrayLike,
    model: str = "normal",
    h: float = 1.0,
    alpha: float = 0.05,
    mode: str = "per_prediction",
    episode_ids: ArrayLike | None = None,
    *,
    score_name: str = ScoreName.MAX_ABS_COV.value,
    space: str = ScoreSpace.NORMALIZED.value,
    score_settings: dict[str, Any] | None = None,
) -> OODCalibration:
    """Fit the I.D. score model and the threshold of the one-sided likelihood-ratio test.

    Per-step model (both modes): x = g(score), with g the identity (``normal``) or log (``lognormal``);
    mean and std (ddof = 1) of x over all I.D. scores give M_ID = Normal(mean, h * std).

    ``per_prediction`` (the paper's): the one-sided LRT of M_ID against an upward shift rejects for
    x > mean + z_{1-alpha} h std (derivation in the module docstring), so

        threshold = g^{-1}(mean + z_{1-alpha} * h * std),     critical_value = z_{1-alpha}.

    At h = 1 each I.D. prediction is a false alarm with probability about alpha (exactly, if the model
    family is right); h > 1 widens the I.D. model and lowers it.

    ``per_episode``: the test is applied to the running maximum of the scores within an episode. The
    threshold is the finite-sample (split-conformal) quantile of the n I.D. episode maxima M_(1) <= ... <=
    M_(n):

        threshold = M_(k),    k = ceil((n + 1) * (1 - alpha)),

    and critical_value = (g(M_(k)) - mean) / std; for h != 1 the threshold is g^{-1}(mean +
    critical_value * h * std), i.e. h widens the distance to the mean as in the per-prediction mode. At
    h = 1, for a fresh I.D. episode exchangeable with the calibration episodes, P(max > threshold) <= alpha,
    and >= alpha - 1/(n + 1) when there are no ties: a distribution-free guarantee. This is chosen over
    fitting a Normal / log-Normal to the episode maxima because the maximum of T correlated, skewed
    per-step scores has an extreme-value (Gumbel-like) right tail that neither family matches: a Normal fit
    to Gumbel maxima puts its 95 % quantile where the true exceedance rate is about 6.6 %, and the error
    depends on T and on the score's autocorrelation, which a policy's rollouts do not let us model. The
    price is that n >= (1 - alpha) / alpha episodes are needed (19 at alpha = 0.05) and that, for a given
    calibration set, the realised false-alarm rate scatters as Beta(n + 1 - k, k) around alpha (standard
    deviation about sqrt(alpha (1 - alpha) / n), 0.022 for n = 100); use >= 100 episodes where
    possible. The rate holds for episodes of about the calibration length (``mean_episode_length``):
    longer episodes have larger maxima. ``mean``/``std``/``model`` still describe the per-step scores so
    the standardized statistic is comparable between modes.

    Args:
        scores: I.D. per-step scores, shape ``(N,)``, one per prediction, finite (and > 0 for
            ``lognormal``).
        model: ``"normal"`` or ``"lognormal"``.
        h: Widening factor of the I.D. model, > 0.
        alpha: Significance level, in (0, 0.5): per prediction or per episode according to ``mode``.
        mode: ``"per_prediction"`` or ``"per_episode"``.
        episode_ids: Episode label of each score, shape ``(N,)``; required for ``per_episode``, and used
            only to count episodes in ``per_prediction`` mode.
        score_name: Name of the score the values come from (see :class:`ScoreName`).
        space: ``"normalized"`` or ``"unnormalized"`` action space of the covariance.
        score_settings: The scorer's other settings that shape the score's distribution, recorded so
            that a policy can refuse a calibration fitted with different ones (see
            :class:`OODCalibration`).

    Returns:
        The frozen calibration.

    Raises:
        ValueError: On empty, non-1-D or non-finite ``scores``; non-positive scores for ``lognormal``;
            constant scores; ``alpha`` or ``h`` out of range; an unknown ``model``/``mode``/``space``/
            ``score_name``; too few scores or episodes; missing or mismatched ``episode_ids``.
    """
    model_ = _parse_enum(CalibrationModel, model, "model")
    mode_ = _parse_enum(CalibrationMode, mode, "mode")
    _parse_enum(ScoreSpace, space, "space")
    ScoreName.parse(score_name)
    _check_alpha(alpha)
    _check_h(h)

    scores = np.asarray(scores, dtype=np.float64)
    if scores.ndim != 1:
        raise ValueError(
            f"`scores` must have shape (N,), one score per prediction. Got shape {scores.shape}; flatten it "
            "and pass `episode_ids` to keep the episodes."
        )
    if scores.size == 0:
        raise ValueError("`scores` is empty. Record I.D. rollouts before calibrating.")
    if not np.all(np.isfinite(scores)):
        n_bad = int(np.sum(~np.isfinite(scores)))
        raise ValueError(
            f"`scores` must be finite. Got {n_bad} NaN/inf value(s); drop them or check the policy's "
            "ensemble predictions."
        )
    if model_ is CalibrationModel.LOGNORMAL and np.any(scores <= 0):
        raise ValueError(
            f"`scores` must be > 0 for model 'lognormal'. Got minimum {scores.min()!r}; use "
            "`model='normal'` for scores that can be zero or negative (e.g. 'logdet')."
        )
    if scores.size < MIN_CALIBRATION_SAMPLES:
        raise ValueError(
            f"`scores` must hold at least {MIN_CALIBRATION_SAMPLES} samples. Got {scores.size}; record more "
            "I.D. rollouts."
        )
    x = _transform(scores, model_)
    mean = float(np.mean(x))
    std = float(np.std(x, ddof=1))
    if not std > 0:
        raise ValueError("`scores` are all equal (zero spread); cannot fit an I.D. model. Check the policy.")

    n_episodes = None
    labels = None
    if episode_ids is not None:
        episode_ids = np.asarray(episode_ids)
        if episode_ids.shape != scores.shape:
            raise ValueError(
                f"`episode_ids` must have the shape of `scores` {scores.shape}. Got {episode_ids.shape}."
            )
        _, labels = np.unique(episode_ids, return_inverse=True)
        n_episodes = int(labels.max()) + 1

    common = {
        "model": model_.value,
        "mean": mean,
        "std": std,
        "h": float(h),
        "alpha": float(alpha),
        "mode": mode_.value,
        "n_samples": int(scores.size),
        "score_name": ScoreName.parse(score_name).value,
        "space": space,
        "score_settings": score_settings,
        "n_episodes": n_episodes,
    }
    if mode_ is CalibrationMode.PER_PREDICTION:
        critical = float(stats.norm.ppf(1.0 - alpha))
        threshold = _inverse_transform(mean + critical * h * std, model_)
        return OODCalibration(**common, threshold=threshold, critical_value=critical)

    if labels is None:
        raise ValueError(
            "`episode_ids` is required for mode 'per_episode' (the label of the episode of each score)."
        )
    n_min = min_calibration_episodes(alpha)
    if n_episodes < n_min:
        raise ValueError(
            f"mode 'per_episode' at `alpha`={alpha} needs at least {n_min} I.D. episodes (the quantile rank "
            f"ceil((n + 1)(1 - alpha)) must not exceed n). Got {n_episodes}; record more episodes "
            "(>= 100 recommended) or raise `alpha`."
        )
    maxima = np.full(n_episodes, -np.inf)
    np.maximum.at(maxima, labels, scores)  # (n_episodes,)
    rank = _quantile_rank(n_episodes, alpha)
    quantile = float(np.sort(maxima)[rank - 1])
    critical = (float(_transform(np.float64(quantile), model_)) - mean) / std
    if not critical > 0:
        raise ValueError(
            "The per-episode maximum quantile is not above the mean per-step score; the scores look "
            "degenerate (nearly constant within episodes). Check the policy or use mode 'per_prediction'."
        )
    threshold = quantile if h == 1.0 else _inverse_transform(mean + critical * h * std, model_)
    return OODCalibration(
        **common,
        threshold=threshold,
        critical_value=critical,
        quantile_rank=rank,
        mean_episode_length=scores.size / n_episodes,
    )


# The test.


def standardized_score(score: ArrayLike, calibration: OODCalibration) -> np.ndarray | float:
    """z = (g(score) - mean) / (h * std): the score in units of the widened I.D. spread.

    Args:
        score: Score(s), any shape ``(...)``. In ``per_episode`` mode pass the running maximum.
        calibration: The fitted calibration.

    Returns:
        z with the shape of ``score`` (a float for a scalar input). For ``lognormal``, score <= 0 gives
        -inf; NaN stays NaN.
    """
    x = _transform(np.asarray(score, dtype=np.float64), CalibrationModel(calibration.model))
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
        episode_ids = np.asarray(episode_ids)
        if episode_ids.shape != scores.shape:
            raise ValueError(
                f"`episode_ids` must have the shape of `scores` {scores.shape}. Got {episode_ids.shape}."
            )
        _, labels = np.unique(episode_ids, return_inverse=True)
        n_episodes = int(labels.max()) + 1
        episode_alarm = np.zeros(n_episodes, dtype=bool)
        np.logical_or.at(episode_alarm, labels, alarms)
        per_episode = float(np.mean(episode_alarm))
    return FalseAlarmRates(float(np.mean(alarms)), per_episode, int(scores.size), n_episodes)


# The gate.


@dataclass
class OODGate:
    """Stateful O.O.D. gate for one episode at a time, to be held by a policy.

    Call :meth:`update` with each prediction's score; it returns the current test decision. Once a
    decision is O.O.D. the gate is ``released`` (latched) until :meth:`reset`, which the policy calls at
    the start of every episode.

    ``enforce`` is carried for the policy and does not change what the gate computes: with
    ``enforce=False`` the policy only reports ``last_score``, ``threshold`` and ``decision`` (the paper's
    experiments); with ``enforce=True`` the policy stops commanding motion (it holds the current pose)
    while ``released`` is True, handing control to the surgeon. Enforcing needs a calibration; without one
    (allowed only with ``enforce=False``, e.g. while recording calibration rollouts) the gate records
    scores and never decides O.O.D.

    Args:
        calibration: The fitted calibration, or None to only record scores.
        enforce: Whether the policy should act on ``released`` (see above).

    Attributes:
        last_score: Score of the latest update (NaN before the first).
        running_max: Maximum score since :meth:`reset` (-inf before the first; NaN scores are skipped).
        last_statistic: Standardized statistic z of the tested value (score or running max) of the latest
            update (NaN before the first or without calibration).
        decision: Test decision of the latest update: per prediction, ``last_score > threshold``; per
            episode, ``running_max > threshold``. NaN scores decide O.O.D.
        released: True from the first O.O.D. decision until :meth:`reset`.
        n_updates: Number of updates since :meth:`reset`.
        released_at: Index (0-based, since reset) of the update that released control, or None.
    """

    calibration: OODCalibration | None = None
    enforce: bool = False
    last_score: float = field(default=math.nan, init=False)
    running_max: float = field(default=-math.inf, init=False)
    last_statistic: float = field(default=math.nan, init=False)
    decision: bool = field(default=False, init=False)
    released: bool = field(default=False, init=False)
    n_updates: int = field(default=0, init=False)
    released_at: int | None = field(default=None, init=False)

    def __post_init__(self):
        if self.enforce and self.calibration is None:
            raise ValueError(f"An enforced OOD gate needs a calibration. {_CALIBRATE_HINT}")

    @property
    def threshold(self) -> float:
        """Score threshold of the test (NaN without calibration)."""
        return math.nan if self.calibration is None else self.calibration.threshold

    @property
    def mode(self) -> str | None:
        """Calibration mode, or None without calibration."""
        return None if self.calibration is None else self.calibration.mode

    def update(self, score: float) -> bool:
        """Record one prediction's score and return the test decision (True = O.O.D.).

        Args:
            score: The prediction's uncertainty score (a scalar, e.g. from :func:`compute_score`).

        Returns:
            The decision of this update; see ``decision`` and ``released``.
        """
        score = float(np.asarray(score, dtype=np.float64).reshape(()))
        self.last_score = score
        if not math.isnan(score):
            self.running_max = max(self.running_max, score)
        if self.calibration is None:
            self.decision = False
        else:
            per_episode = self.calibration.mode == CalibrationMode.PER_EPISODE
            tested = score if math.isnan(score) or not per_episode else self.running_max
            self.decision = likelihood_ratio_test(tested, self.calibration)
            self.last_statistic = standardized_score(tested, self.calibration)
        if self.decision and not self.released:
            self.released = True
            self.released_at = self.n_updates
        self.n_updates += 1
        return self.decision

    def reset(self) -> None:
        """Start a new episode: clear the scores, the decision and the latch (calibration is kept)."""
        self.last_score = math.nan
        self.running_max = -math.inf
        self.last_statistic = math.nan
        self.decision = False
        self.released = False
        self.n_updates = 0
        self.released_at = None


# Save / load.


class CalibrationNotFoundError(FileNotFoundError):
    """No calibration file in a policy directory; the message says how to create one."""


def save_calibration(
    calibration: OODCalibration, directory: str | os.PathLike, filename: str = CALIBRATION_FILENAME
) -> Path:
    """Write ``calibration`` to ``directory / filename`` (created if needed, written atomically).

    Args:
        calibration: The calibration to save.
        directory: Directory, typically the pretrained policy directory.
        filename: File name inside ``directory`` (the policy's ``ood.calibration_file``).

    Returns:
        Path of the written file.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / filename
    text = json.dumps(calibration.to_dict(), indent=2, allow_nan=False) + "\n"
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=f".{filename}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def load_calibration(directory: str | os.PathLike, filename: str = CALIBRATION_FILENAME) -> OODCalibration:
    """Read the calibration saved by :func:`save_calibration` in ``directory``.

    Args:
        directory: Directory holding ``filename`` (typically the pretrained policy directory).
        filename: File name inside ``directory`` (the policy's ``ood.calibration_file``).

    Returns:
        The validated calibration.

    Raises:
        CalibrationNotFoundError: If the file does not exist (a FileNotFoundError; the message says how to
            calibrate).
        ValueError: If the file is not valid JSON, misses a key, has an unknown key, an invalid value or a
            different format ``version``; the message names the key.
    """
    path = Path(directory) / filename
    if not path.is_file():
        raise CalibrationNotFoundError(f"No OOD calibration at {path}. {_CALIBRATE_HINT}")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise ValueError(
            f"OOD calibration {path} is not valid JSON ({e}). Re-run `lerobot-suture calibrate "
            "--policy.path=DIR`."
        ) from e
    try:
        return OODCalibration.from_dict(data)
    except (TypeError, ValueError) as e:
        raise ValueError(f"Invalid OOD calibration {path}: {e}") from e
