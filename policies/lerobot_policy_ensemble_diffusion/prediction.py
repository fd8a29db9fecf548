#!/usr/bin/env python

# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.
"""One ensemble prediction (the statistics of every member's sampled chunks) and its uncertainty score
under a choice of score (`SCORE_CHOICES`: which score, in which action space, of which covariance, over
which steps)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from torch import Tensor

from lerobot_suture.safety.ood.score import score_tensor

from .configuration_ensemble_diffusion import SCORE_CHOICES
from .ensemble_stats import EnsembleActionStats


@dataclass(frozen=True)
class EnsemblePrediction:
    """One ensemble prediction: statistics of every member's sampled chunks for one observation batch.

    Attributes:
        normalized: statistics in the policy's normalized action space (what the members predict).
        unnormalized: the same in dataset units (the postprocessor's inverse normalization); None when
            the policy holds no action statistics (built without `dataset_stats` and never trained/loaded).
        score: (B,) the configured uncertainty score (sigma_hat by default), one per batch element.
        score_name: the score's name (`config.uncertainty_score`).
        score_space: "normalized" or "unnormalized".
        score_source: "total", "epistemic" or "aleatoric".
        action_steps: the slice of the T = horizon predicted steps that `select_action` executes.
    """

    normalized: EnsembleActionStats
    unnormalized: EnsembleActionStats | None
    score: Tensor
    score_name: str
    score_space: str
    score_source: str
    action_steps: slice


def score_ensemble_stats(
    normalized: EnsembleActionStats,
    unnormalized: EnsembleActionStats | None,
    action_steps: slice,
    choice: Mapping[str, str],
    *,
    logdet_eps: float,
) -> Tensor:
    """(B,) the uncertainty score of one prediction's statistics under one choice of score.

    Args:
        normalized: the statistics in the normalized action space.
        unnormalized: the same in dataset units; None when the policy holds no action statistics.
        action_steps: the executed steps of the T predicted ones (used with `uncertainty_steps`="action").
        choice: a value for each of `SCORE_CHOICES`' fields (`uncertainty_score`, `uncertainty_space`,
            `uncertainty_source`, `uncertainty_steps`; see `EnsembleDiffusionConfig`).
        logdet_eps: the config's `logdet_eps`.
    """
    if set(choice) != set(SCORE_CHOICES):
        raise ValueError(f"A score choice names each of {list(SCORE_CHOICES)}. Got {sorted(choice)}.")
    for name, allowed in SCORE_CHOICES.items():
        if choice[name] not in allowed:
            raise ValueError(f"`{name}` must be one of {list(allowed)}. Got {choice[name]!r}.")
    scored = normalized
    if choice["uncertainty_space"] == "unnormalized":
        if unnormalized is None:
            raise ValueError(
                "`uncertainty_space`='unnormalized' needs the action statistics, which this policy does not "
                "hold: build it with `dataset_stats` (lerobot-train does) or load a trained checkpoint."
            )
        scored = unnormalized
    if choice["uncertainty_steps"] == "action":
        scored = scored.select_steps(action_steps)
    source = choice["uncertainty_source"]
    if source == "aleatoric" and scored.aleatoric is None:
        raise ValueError(
            "`uncertainty_source`='aleatoric' needs `uncertainty_samples_per_member` >= 2 (the members' own "
            "covariances need two samples each)."
        )
    cov = {"total": scored.covariance, "epistemic": scored.epistemic, "aleatoric": scored.aleatoric}[source]
    return score_tensor(cov, choice["uncertainty_score"], logdet_eps=logdet_eps)
