"""Random network distillation on the members' observation embeddings (Burda et al., 2019), as
FAIL-Detect (Xu et al., 2025) uses it to flag a diffusion policy's unfamiliar states.

A target MLP f with fixed random weights maps the standardized embedding z (the members' embeddings
concatenated, standardized per feature on the nominal predictions) to R^d; a predictor g of the same shape
is trained to match f on the nominal predictions only. The score is the prediction error

    score(z) = mean_i (g(z) - f(z))_i^2,

small where g has seen inputs like z and large elsewhere: f is a fixed random function, so g can only
match it where it was trained.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from lerobot_suture.detectors.base import PredictionFeatures, require


def _mlp(d_in: int, hidden: int, d_out: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(d_in, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, d_out)
    )


@dataclass
class RNDFit:
    """A fitted RND: the standardization, the random target and the trained predictor."""

    mean: np.ndarray  # (D,)
    scale: np.ndarray  # (D,)
    target: nn.Module
    predictor: nn.Module
    final_loss: float


def fit_rnd(
    x: np.ndarray, hidden: int = 128, out_dim: int = 32, steps: int = 500, lr: float = 1e-3, seed: int = 0
) -> RNDFit:
    """Train the predictor on nominal inputs ``x`` (M, D) for ``steps`` full-batch Adam steps."""
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError(f"`x` must have shape (M, D) with M >= 2. Got {x.shape}.")
    mean, scale = x.mean(axis=0), x.std(axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    generator = torch.Generator().manual_seed(seed)  # own RNG: fitting leaves the global state alone
    target, predictor = _mlp(x.shape[1], hidden, out_dim), _mlp(x.shape[1], hidden, out_dim)
    with torch.no_grad():
        for p in [*target.parameters(), *predictor.parameters()]:
            p.copy_(torch.randn(p.shape, generator=generator) * (1.0 / max(p.shape[-1], 1)) ** 0.5)
    target.requires_grad_(False)
    z = torch.as_tensor((x - mean) / scale, dtype=torch.float32)  # (M, D)
    with torch.no_grad():
        y = target(z)  # (M, d)
    optimizer = torch.optim.Adam(predictor.parameters(), lr=lr)
    loss = torch.tensor(float("nan"))
    with torch.enable_grad():
        for _ in range(steps):
            optimizer.zero_grad()
            loss = torch.mean((predictor(z) - y) ** 2)
            loss.backward()
            optimizer.step()
    predictor.requires_grad_(False)
    return RNDFit(mean=mean, scale=scale, target=target, predictor=predictor, final_loss=float(loss.detach()))


def rnd_error(fit: RNDFit, x: np.ndarray) -> np.ndarray:
    """The prediction error of each row of ``x`` (..., D): shape (...)."""
    z = torch.as_tensor((np.asarray(x, dtype=np.float64) - fit.mean) / fit.scale, dtype=torch.float32)
    with torch.no_grad():
        return torch.mean((fit.predictor(z) - fit.target(z)) ** 2, dim=-1).numpy().astype(np.float64)


@dataclass
class RNDDetector:
    """RND error on the members' concatenated embeddings.

    Args:
        hidden: width of the two hidden layers of target and predictor, >= 1.
        out_dim: output size d of target and predictor, >= 1.
        steps: full-batch Adam steps of the predictor, >= 1.
        lr: Adam learning rate, > 0.
        seed: seed of the random target and the predictor's initial weights.
    """

    name: str = "rnd"
    hidden: int = 128
    out_dim: int = 32
    steps: int = 500
    lr: float = 1e-3
    seed: int = 0
    fitted: RNDFit | None = field(default=None, repr=False)

    def __post_init__(self):
        for key in ("hidden", "out_dim", "steps"):
            if getattr(self, key) < 1:
                raise ValueError(f"`{key}` must be >= 1. Got {getattr(self, key)}.")
        if not self.lr > 0:
            raise ValueError(f"`lr` must be > 0. Got {self.lr}.")

    def fit(self, features: Sequence[PredictionFeatures]) -> RNDDetector:
        x = np.stack([require(f.embedding, self.name, "the members' embeddings").ravel() for f in features])
        self.fitted = fit_rnd(x, self.hidden, self.out_dim, self.steps, self.lr, self.seed)
        return self

    def score(self, features: PredictionFeatures) -> float:
        if self.fitted is None:
            raise ValueError(f"Detector {self.name!r} is not fitted; call `fit` on nominal predictions.")
        return float(
            rnd_error(self.fitted, require(features.embedding, self.name, "the members' embeddings").ravel())
        )
