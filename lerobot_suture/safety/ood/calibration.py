"""Calibration of the O.O.D. test: a model of in-distribution (I.D.) scores and the test's threshold.

I.D. model (paper: M_ID = Normal(mean, h * std)). Let x = g(score), with g the identity
(``model="normal"``) or the natural log (``model="lognormal"``, since the score is positive and
right-skewed). Under H0 (I.D.) x ~ N(m, (h s)^2), with m, s the sample mean and standard deviation of
g(I.D. scores) and h > 0 a widening factor. The one-sided likelihood-ratio test at level alpha rejects for
score > threshold = g^{-1}(m + z_{1-alpha} * h * s) (derivation in
:mod:`lerobot_suture.safety.ood.likelihood_ratio`).

Two calibration modes:

* ``per_prediction`` (the paper's): every prediction is tested at level alpha. On an I.D. episode of T
  predictions the chance of at least one false alarm is up to 1 - (1 - alpha)^T (0.98 for T = 80 at
  alpha = 0.05 with independent scores), so a latched gate stops most long I.D. episodes.
* ``per_episode``: the test is applied to the running maximum of the scores within an episode, with a
  threshold chosen so that the per-episode false-alarm rate on I.D. episodes is about alpha; see
  :func:`fit_calibration` for the finite-sample quantile used and why.

A gate that latches (:class:`~lerobot_suture.safety.ood.gate.OODGate`) releases control on an episode
iff the episode's maximum score exceeds the threshold in both modes, so the modes differ only in how the
threshold is chosen.
"""

import math
import numbers
from dataclasses import MISSING, asdict, dataclass, fields
from enum import StrEnum
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats

from lerobot_suture.safety.ood.score import ScoreName, ScoreSpace

__all__ = [
    "CALIBRATE_HINT",
    "CALIBRATION_FORMAT_VERSION",
    "CalibrationMode",
    "CalibrationModel",
    "MIN_CALIBRATION_SAMPLES",
    "OODCalibration",
    "conformal_episode_threshold",
    "default_model",
    "episode_labels",
    "fit_calibration",
    "min_calibration_episodes",
    "score_transform",
]

CALIBRATION_FORMAT_VERSION = 1
"""Version of the calibration JSON format; bumped on any incompatible change."""

MIN_CALIBRATION_SAMPLES = 10
"""Fewest per-step I.D. scores accepted by :func:`fit_calibration` (a floor, not a recommendation)."""

CALIBRATE_HINT = (
    "Calibrate the policy first with `lerobot-suture calibrate --policy.path=DIR` (DIR is the pretrained "
    "policy directory), or set `ood.enforce=false` to only report scores."
)


class CalibrationModel(StrEnum):
    """Family of the I.D. score model: Normal on the score, or Normal on the log score."""

    NORMAL = "normal"
    LOGNORMAL = "lognormal"


class CalibrationMode(StrEnum):
    """What the threshold is applied to: each prediction's score, or the running maximum in an episode."""

    PER_PREDICTION = "per_prediction"
    PER_EPISODE = "per_episode"


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


def score_transform(scores: np.ndarray, model: CalibrationModel) -> np.ndarray:
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


def episode_labels(episode_ids: ArrayLike, scores: np.ndarray) -> tuple[np.ndarray, int]:
    """The episode index (0 to n - 1) of each score, shape ``(N,)``, and the number of episodes n.

    Raises:
        ValueError: If ``episode_ids`` does not have the shape of ``scores``.
    """
    episode_ids = np.asarray(episode_ids)
    if episode_ids.shape != scores.shape:
        raise ValueError(
            f"`episode_ids` must have the shape of `scores` {scores.shape}. Got {episode_ids.shape}."
        )
    _, labels = np.unique(episode_ids, return_inverse=True)
    return labels, int(labels.max()) + 1


def _quantile_rank(n: int, alpha: float) -> int:
    """k = ceil((n + 1)(1 - alpha)), guarded against float round-up at exact integers."""
    return math.ceil((n + 1) * (1.0 - alpha) - 1e-9)


def conformal_episode_threshold(episode_maxima: ArrayLike, alpha: float) -> float:
    """The ``per_episode`` threshold of :func:`fit_calibration` at h = 1, for any score: the
    split-conformal quantile M_(k), k = ceil((n + 1)(1 - alpha)), of n I.D. episode maxima.

    A fresh exchangeable I.D. episode's maximum exceeds it with probability <= alpha, whatever the score's
    distribution, which is why detectors with unlike scores can share it.

    Raises:
        ValueError: On non-finite maxima, ``alpha`` out of (0, 0.5) or fewer than
            :func:`min_calibration_episodes` episodes.
    """
    maxima = np.asarray(episode_maxima, dtype=np.float64)
    _check_alpha(alpha)
    if maxima.ndim != 1 or not np.all(np.isfinite(maxima)):
        raise ValueError(f"`episode_maxima` must be a finite 1-D array, one per episode. Got {maxima!r}.")
    n_min = min_calibration_episodes(alpha)
    if maxima.size < n_min:
        raise ValueError(
            f"A per-episode threshold at `alpha`={alpha} needs at least {n_min} I.D. episodes. Got "
            f"{maxima.size}; record more episodes (>= 100 recommended) or raise `alpha`."
        )
    return float(np.sort(maxima)[_quantile_rank(maxima.size, alpha) - 1])


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
        actual = float(score_transform(np.float64(self.threshold), model))
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
    x = score_transform(scores, model_)
    mean = float(np.mean(x))
    std = float(np.std(x, ddof=1))
    if not std > 0:
        raise ValueError("`scores` are all equal (zero spread); cannot fit an I.D. model. Check the policy.")

    n_episodes = None
    labels = None
    if episode_ids is not None:
        labels, n_episodes = episode_labels(episode_ids, scores)

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
    critical = (float(score_transform(np.float64(quantile), model_)) - mean) / std
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
