"""Mahalanobis distance of the members' observation embeddings to the nominal ones (Lee et al., 2018).

Per member n, the embeddings e (G,) of nominal predictions are standardized per feature (mean m, scale s)
and fitted with a Gaussian whose covariance is the Ledoit-Wolf shrinkage estimate (Ledoit and Wolf,
2004): with the empirical covariance C of z = (e - m) / s and mu = tr(C) / G,

    Sigma = (1 - rho) C + rho mu I,        rho in [0, 1] chosen to minimise the expected Frobenius error.

A few hundred nominal predictions do not fill a G-dimensional embedding (G is in the hundreds), so C is
singular and needs the shrinkage. The score is the mean over members of d_n = sqrt(z^T Sigma^-1 z). The
standardization makes it invariant to any per-feature affine map of the embeddings.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from lerobot_suture.detectors.base import PredictionFeatures, require


def ledoit_wolf(x: np.ndarray) -> tuple[np.ndarray, float]:
    """Shrunk covariance (G, G) of centred samples ``x`` (M, G) and the shrinkage rho in [0, 1]."""
    x = np.asarray(x, dtype=np.float64)
    m, g = x.shape
    emp = x.T @ x / m  # (G, G)
    mu = np.trace(emp) / g
    x2 = x**2
    beta = (np.sum(x2.T @ x2) / m - np.sum(emp**2)) / m  # variance of the entries of emp, summed
    delta = np.sum((emp - mu * np.eye(g)) ** 2)  # distance of emp to the target mu I
    rho = 0.0 if delta == 0 else float(np.clip(beta / delta, 0.0, 1.0))
    return (1.0 - rho) * emp + rho * mu * np.eye(g), rho


@dataclass(frozen=True)
class GaussianFit:
    """Per-feature standardization and the precision of the shrunk covariance, for one embedding space."""

    mean: np.ndarray  # (G,)
    scale: np.ndarray  # (G,)
    precision: np.ndarray  # (G, G)
    shrinkage: float


def fit_gaussian(embeddings: np.ndarray) -> GaussianFit:
    """Fit ``embeddings`` (M, G), M >= 2, of nominal predictions."""
    e = np.asarray(embeddings, dtype=np.float64)
    if e.ndim != 2 or e.shape[0] < 2:
        raise ValueError(f"`embeddings` must have shape (M, G) with M >= 2. Got {e.shape}.")
    mean = e.mean(axis=0)
    scale = e.std(axis=0)
    scale = np.where(scale > 0, scale, 1.0)  # a constant feature stays 0 after centring
    cov, rho = ledoit_wolf((e - mean) / scale)
    return GaussianFit(mean=mean, scale=scale, precision=np.linalg.pinv(cov, hermitian=True), shrinkage=rho)


def mahalanobis_distance(fit: GaussianFit, embeddings: np.ndarray) -> np.ndarray:
    """sqrt(z^T Sigma^-1 z) of each row of ``embeddings`` (..., G): shape (...)."""
    z = (np.asarray(embeddings, dtype=np.float64) - fit.mean) / fit.scale
    return np.sqrt(np.maximum(np.einsum("...i,ij,...j->...", z, fit.precision, z), 0.0))


@dataclass
class MahalanobisDetector:
    """Mean over members of the Mahalanobis distance of their embeddings to the nominal predictions'."""

    name: str = "mahalanobis"
    fits: list[GaussianFit] = field(default_factory=list, repr=False)

    def fit(self, features: Sequence[PredictionFeatures]) -> MahalanobisDetector:
        e = np.stack([require(f.embedding, self.name, "the members' embeddings") for f in features])
        self.fits = [fit_gaussian(e[:, n]) for n in range(e.shape[1])]  # one per member: own encoder
        return self

    def score(self, features: PredictionFeatures) -> float:
        if not self.fits:
            raise ValueError(f"Detector {self.name!r} is not fitted; call `fit` on nominal predictions.")
        e = require(features.embedding, self.name, "the members' embeddings")  # (N, G)
        return float(np.mean([mahalanobis_distance(f, e[n]) for n, f in enumerate(self.fits)]))
