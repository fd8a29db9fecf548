"""One diffusion policy's own sample spread: the aleatoric-only detector.

A single member draws K' chunks on the same observation (different diffusion noise); the score is
sigma_hat = max_t max_ij |cov_k(x_{k,t})[i, j]| of those chunks. Without an ensemble this is all a
diffusion policy can say about itself: it measures how many ways the policy sees to act, not whether it
has seen states like this one, so it is the baseline the ensemble's epistemic part is compared with.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lerobot_suture.detectors.base import PredictionFeatures, require
from lerobot_suture.detectors.covariance import sample_covariance
from lerobot_suture.safety.ood.score import score_max_abs_cov


def single_member_spread(samples: np.ndarray) -> float:
    """sigma_hat of the covariance of one member's (K', T, A) chunks, K' >= 2."""
    return float(score_max_abs_cov(sample_covariance(samples)))


@dataclass
class SingleMemberSpreadDetector:
    """sigma_hat of member 0's own K' samples (``single_member_samples`` captured at inference)."""

    name: str = "single_member_spread"

    def fit(self, features: Sequence[PredictionFeatures]) -> SingleMemberSpreadDetector:
        return self

    def score(self, features: PredictionFeatures) -> float:
        return single_member_spread(require(features.single_member_samples, self.name, "member 0's samples"))
