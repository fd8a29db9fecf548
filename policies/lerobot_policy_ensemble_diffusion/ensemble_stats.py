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
"""Statistics of an ensemble's action samples, as pure torch functions.

Notation: B batch, N members, K samples per member (different diffusion noise), T predicted steps,
A action dimensions. Member n's k-th sampled chunk is x_{n,k} (T, A).

- Ensemble mean per step: mu_t = mean_{n,k} x_{n,k,t}                                      (T, A)
- The paper's ensemble covariance (K = 1): Sigma_t = cov_n(x_{n,t})                            (T, A, A)
- Law of total covariance (K > 1):
      Sigma_t = E_n[cov_k(x_{n,k,t})] + cov_n(E_k[x_{n,k,t}])
              =      aleatoric       +       epistemic
  aleatoric: the members' own spread (many valid ways to act, multimodality);
  epistemic: disagreement between the members' means (the state is unlike the training data).
  Each term is estimated with Bessel correction `correction` (1: unbiased, as `np.cov`; 0: population). With
  `correction=0` the sum equals the population covariance of all N*K samples pooled (an exact identity).
  With K = 1 the aleatoric term is not identifiable and the total is the epistemic term, the paper's Sigma.

The scores of these covariances are `lerobot_suture.safety.ood.score.score_tensor` (one implementation,
shared with the gate's numpy side).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor


def ensemble_mean(samples: Tensor, dim: int = -3, keepdim: bool = False) -> Tensor:
    """Mean over the member axis, exact when all members agree.

    Computed as x_0 + mean(x_n - x_0): identical members give exactly their common value (and so an exactly
    zero covariance), where a plain sum-then-divide can be off by rounding.

    Args:
        samples: (..., N, T, A) samples; the member axis is `dim` (default: third from last).
    Returns:
        (..., T, A) mean ((..., 1, T, A) with `keepdim`).
    """
    shift = samples.narrow(dim, 0, 1)  # (..., 1, T, A)
    mean = shift + (samples - shift).mean(dim=dim, keepdim=True)
    return mean if keepdim else mean.squeeze(dim)


def ensemble_covariance(samples: Tensor, correction: int = 1) -> Tensor:
    """Per-step covariance across the member axis.

    Args:
        samples: (..., N, T, A) samples, N >= correction + 1.
        correction: Bessel correction (1: unbiased, divides by N - 1, as `np.cov`; 0: divides by N).
    Returns:
        (..., T, A, A) covariance, symmetric positive semi-definite.
    """
    n = samples.shape[-3]
    if n - correction < 1:
        raise ValueError(
            f"A covariance with correction={correction} needs at least {correction + 1} samples. Got {n}."
        )
    centered = samples - ensemble_mean(samples, keepdim=True)  # (..., N, T, A)
    cov = torch.einsum("...nta,...ntb->...tab", centered, centered) / (n - correction)  # (..., T, A, A)
    return 0.5 * (cov + cov.transpose(-1, -2))  # exact symmetry despite rounding


def total_covariance_split(samples: Tensor, correction: int = 1) -> tuple[Tensor, Tensor, Tensor]:
    """Split the ensemble covariance by the law of total covariance.

    Args:
        samples: (..., N, K, T, A) samples, K per member, K >= 2 (for `correction=1`), N >= 1.
        correction: Bessel correction of both terms (see module docstring).
    Returns:
        aleatoric: (..., T, A, A) mean over members of each member's covariance over its K samples.
        epistemic: (..., T, A, A) covariance over members of each member's mean over its K samples; zero
            for a single member, which has none to disagree with.
        total: (..., T, A, A) aleatoric + epistemic.
    """
    member_means = ensemble_mean(samples)  # (..., N, T, A): mean over each member's K samples
    within = ensemble_covariance(samples, correction=correction)  # (..., N, T, A, A)
    aleatoric = within.mean(dim=-4)  # (..., T, A, A)
    if member_means.shape[-3] == 1:
        return aleatoric, torch.zeros_like(aleatoric), aleatoric
    epistemic = ensemble_covariance(member_means, correction=correction)  # (..., T, A, A)
    return aleatoric, epistemic, aleatoric + epistemic


@dataclass(frozen=True)
class EnsembleActionStats:
    """The statistics of one ensemble prediction, all in one action space.

    Attributes:
        samples: (B, N, K, T, A) every member's K sampled chunks.
        member_mean: (B, N, T, A) each member's mean chunk (its single sample when K = 1).
        mean: (B, T, A) ensemble mean, the chunk used for control.
        covariance: (B, T, A, A) total covariance (the paper's Sigma_t when K = 1).
        epistemic: (B, T, A, A) covariance of the members' means (equals `covariance` when K = 1).
        aleatoric: (B, T, A, A) mean of the members' own covariances; None when K = 1.
    """

    samples: Tensor
    member_mean: Tensor
    mean: Tensor
    covariance: Tensor
    epistemic: Tensor
    aleatoric: Tensor | None

    def affine(self, scale: Tensor, offset: Tensor) -> EnsembleActionStats:
        """The same statistics after the per-dimension map x -> x * scale + offset.

        Args:
            scale: (A,) per action dimension.
            offset: (A,) per action dimension.
        """
        outer = scale[:, None] * scale[None, :]  # (A, A): D Sigma D with D = diag(scale)
        return EnsembleActionStats(
            samples=self.samples * scale + offset,
            member_mean=self.member_mean * scale + offset,
            mean=self.mean * scale + offset,
            covariance=self.covariance * outer,
            epistemic=self.epistemic * outer,
            aleatoric=None if self.aleatoric is None else self.aleatoric * outer,
        )

    def select_steps(self, steps: slice) -> EnsembleActionStats:
        """The statistics of the predicted steps `steps` only (slices the T axis)."""
        return EnsembleActionStats(
            samples=self.samples[..., steps, :],
            member_mean=self.member_mean[..., steps, :],
            mean=self.mean[:, steps],
            covariance=self.covariance[:, steps],
            epistemic=self.epistemic[:, steps],
            aleatoric=None if self.aleatoric is None else self.aleatoric[:, steps],
        )

    def to(self, *args, **kwargs) -> EnsembleActionStats:
        """Move every tensor (`Tensor.to` arguments)."""
        return EnsembleActionStats(
            **{
                f.name: None if getattr(self, f.name) is None else getattr(self, f.name).to(*args, **kwargs)
                for f in fields(self)
            }
        )


def compute_ensemble_stats(samples: Tensor, correction: int = 1) -> EnsembleActionStats:
    """All statistics of a batch of ensemble samples.

    Args:
        samples: (B, N, K, T, A) samples, N >= 2, or N = 1 with K >= 2.
        correction: Bessel correction of the covariances.
    Returns:
        EnsembleActionStats; with K = 1 `covariance` is the paper's ensemble covariance over the N members.
    """
    member_mean = ensemble_mean(samples, dim=2)  # (B, N, T, A)
    mean = ensemble_mean(member_mean)  # (B, T, A)
    if samples.shape[2] == 1:
        epistemic = ensemble_covariance(member_mean, correction=correction)  # (B, T, A, A)
        return EnsembleActionStats(samples, member_mean, mean, epistemic, epistemic, None)
    aleatoric, epistemic, total = total_covariance_split(samples, correction=correction)  # 3 x (B, T, A, A)
    return EnsembleActionStats(samples, member_mean, mean, total, epistemic, aleatoric)
