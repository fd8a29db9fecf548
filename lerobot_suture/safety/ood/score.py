"""Uncertainty scores of an ensemble's action covariance, batched over leading axes.

Scores (shape ``(..., T, A, A)`` -> ``(...)``):

    max_abs_cov   sigma_hat = max_t max_{i,j} |Sigma_t[i, j]|          (the paper's score)
    trace         max_t tr(Sigma_t)                                    (total variance)
    logdet        max_t log det(Sigma_t + eps I)                       (log generalised variance)

Scores are unit-free when the covariance is computed in the policy's normalized action space (the
default, recorded as ``space="normalized"`` in the calibration).
"""

from collections.abc import Callable
from enum import StrEnum

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "LOGDET_EPS",
    "ScoreName",
    "ScoreSpace",
    "compute_score",
    "get_score_function",
    "score_logdet",
    "score_max_abs_cov",
    "score_tensor",
    "score_trace",
]

LOGDET_EPS = 1e-6
"""Default diagonal regulariser for :func:`score_logdet`: N ensemble members give rank <= N - 1."""


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


def _torch():
    import torch  # imported when a score is computed: the rest of the gate is numpy

    return torch


def _logdet_terms(cov, eps: float):
    """(sign, log|det|) of ``cov + eps I`` per step, ``(..., T)`` each (torch)."""
    torch = _torch()
    eye = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
    return torch.linalg.slogdet(cov + eps * eye)


def score_tensor(cov, name: "str | ScoreName", logdet_eps: float = LOGDET_EPS):
    """The score ``name`` of a torch covariance ``cov``, ``(..., T, A, A)`` -> ``(...)``, on its device and
    in its dtype: the one implementation of every score (the policy scores its predictions with it, the
    numpy functions below wrap it).
    """
    name = ScoreName.parse(name)
    if name is ScoreName.MAX_ABS_COV:
        return cov.abs().amax(dim=(-3, -2, -1))
    if name is ScoreName.TRACE:
        return cov.diagonal(dim1=-2, dim2=-1).sum(dim=-1).amax(dim=-1)
    return _logdet_terms(cov, logdet_eps).logabsdet.amax(dim=-1)


def _numpy_score(cov: ArrayLike, name: "ScoreName", eps: float = LOGDET_EPS) -> np.ndarray:
    torch = _torch()
    return score_tensor(torch.from_numpy(_as_covariance(cov)), name, eps).numpy()


def score_max_abs_cov(cov: ArrayLike) -> np.ndarray:
    """The paper's score: sigma_hat = max over steps t and entries (i, j) of |Sigma_t[i, j]|.

    Args:
        cov: Ensemble action covariance per predicted step, shape ``(..., T, A, A)``.

    Returns:
        Score of shape ``(...)`` (a 0-d value for an unbatched ``(T, A, A)`` input), >= 0. NaN entries
        propagate to NaN, which the test treats as O.O.D.
    """
    return _numpy_score(cov, ScoreName.MAX_ABS_COV)


def score_trace(cov: ArrayLike) -> np.ndarray:
    """Total variance: max over steps t of tr(Sigma_t).

    Args:
        cov: Ensemble action covariance per predicted step, shape ``(..., T, A, A)``.

    Returns:
        Score of shape ``(...)``, >= 0 for positive semi-definite ``cov``.
    """
    return _numpy_score(cov, ScoreName.TRACE)


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
    sign, logabsdet = _logdet_terms(_torch().from_numpy(cov), eps)  # (..., T)
    if bool(((sign <= 0) & logabsdet.isfinite()).any()):
        raise ValueError(
            f"`cov` + {eps} * I must be positive definite for `score_logdet`; got a non-positive "
            "determinant. Pass a covariance (positive semi-definite) or raise `eps`."
        )
    return logabsdet.amax(dim=-1).numpy()


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


class ScoreSpace(StrEnum):
    """Space in which the ensemble covariance (and so the score) was computed."""

    NORMALIZED = "normalized"
    UNNORMALIZED = "unnormalized"
