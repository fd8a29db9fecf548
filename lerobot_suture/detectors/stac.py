"""Temporal consistency of successive action chunks (STAC, from Sentinel: Agia et al., 2024), as a detector of
the study: the score is :mod:`lerobot_suture.safety.ood.stac_score`'s, which the STAC gate reads too.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from lerobot_suture.detectors.base import PredictionFeatures
from lerobot_suture.safety.ood.stac_score import chunk_overlap, mmd_squared


@dataclass
class TemporalConsistencyDetector:
    """Squared MMD between the overlapping parts of successive chunks of one episode.

    Args:
        bandwidth: per-dimension kernel bandwidth in normalized action units, > 0 (actions are normalized
            to about [-1, 1], so 0.5 tells apart plans that differ by a quarter of the range).
    """

    name: str = "stac"
    bandwidth: float = 0.5

    def __post_init__(self):
        if not self.bandwidth > 0:
            raise ValueError(f"`bandwidth` must be > 0. Got {self.bandwidth}.")

    def fit(self, features: Sequence[PredictionFeatures]) -> TemporalConsistencyDetector:
        return self  # the score compares a prediction with its predecessor only

    def score(self, features: PredictionFeatures) -> float:
        if features.previous_samples is None or features.shift is None:
            return 0.0
        flat = features.samples.reshape(-1, *features.samples.shape[-2:])  # (N*K, T, A)
        prev = features.previous_samples.reshape(-1, *features.previous_samples.shape[-2:])
        a, b = chunk_overlap(prev, flat, features.shift, features.action_start)
        return mmd_squared(a, b, self.bandwidth)
