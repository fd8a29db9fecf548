"""Detectors on the ensemble's action covariance: the total (the paper's score) and its epistemic part.

With every member's K chunks x_{n,k} (law of total covariance, as
``lerobot_policy_ensemble_diffusion.ensemble_stats``, Bessel-corrected):

    epistemic_t = cov_n(mean_k x_{n,k,t})          aleatoric_t = mean_n cov_k(x_{n,k,t})
    total_t     = epistemic_t + aleatoric_t        (= epistemic_t when K = 1, the paper's Sigma_t)

Both detectors score with the paper's sigma_hat = max_t max_ij |Sigma_t[i, j]|
(:func:`~lerobot_suture.safety.ood.score.score_max_abs_cov`) over the whole predicted horizon.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lerobot_suture.detectors.base import PredictionFeatures
from lerobot_suture.safety.ood.score import score_max_abs_cov


def sample_covariance(samples: np.ndarray) -> np.ndarray:
    """(..., T, A, A) covariance over the sample axis of ``samples`` (..., S, T, A), S >= 2 (ddof 1)."""
    samples = np.asarray(samples, dtype=np.float64)
    s = samples.shape[-3]
    if s < 2:
        raise ValueError(f"A covariance needs at least 2 samples. Got {s}.")
    centred = samples - samples.mean(axis=-3, keepdims=True)
    return np.einsum("...sta,...stb->...tab", centred, centred) / (s - 1)


def ensemble_covariances(samples: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """The epistemic and aleatoric covariances of (N, K, T, A) samples, each (T, A, A); aleatoric is
    None when K = 1 (a member's own spread is not identifiable from one chunk)."""
    samples = np.asarray(samples, dtype=np.float64)
    epistemic = sample_covariance(samples.mean(axis=1))  # (T, A, A) over the N member means
    aleatoric = sample_covariance(samples).mean(axis=0) if samples.shape[1] > 1 else None
    return epistemic, aleatoric


def total_covariance_score(samples: np.ndarray) -> float:
    """sigma_hat of the total covariance of (N, K, T, A) samples: the paper's score."""
    epistemic, aleatoric = ensemble_covariances(samples)
    return float(score_max_abs_cov(epistemic if aleatoric is None else epistemic + aleatoric))


def epistemic_score(samples: np.ndarray) -> float:
    """sigma_hat of the epistemic part only (the members' disagreement) of (N, K, T, A) samples."""
    return float(score_max_abs_cov(ensemble_covariances(samples)[0]))


@dataclass
class EnsembleCovarianceDetector:
    """The paper's score and the gate's: sigma_hat of the ensemble's total action covariance."""

    name: str = "ensemble_covariance"

    def fit(self, features: Sequence[PredictionFeatures]) -> EnsembleCovarianceDetector:
        return self  # nothing to learn: the ensemble's spread is the score

    def score(self, features: PredictionFeatures) -> float:
        return total_covariance_score(features.samples)


@dataclass
class EpistemicDetector:
    """sigma_hat of the members' disagreement alone (equal to the total when each member draws K = 1)."""

    name: str = "epistemic"

    def fit(self, features: Sequence[PredictionFeatures]) -> EpistemicDetector:
        return self

    def score(self, features: PredictionFeatures) -> float:
        return epistemic_score(features.samples)
