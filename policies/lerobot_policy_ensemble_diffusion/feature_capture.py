"""What failure detectors read from a prediction besides its action samples, kept without changing it.

Off by default. When on, each prediction leaves "embedding": (B, N, G), each member's observation
embedding (its global conditioning: state and image features over the observation steps), and, with
K' = `single_member_samples` > 0, "single_member_samples": (B, K', T, A), K' further chunks of member 0 in
normalized action space (one diffusion policy's own spread). The extra chunks draw from a generator of
their own, after the ensemble has sampled: the actions and the global random state are those without
capture.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


class FeatureCapture:
    """Holds the capture settings and the last prediction's features (`last`)."""

    def __init__(self, single_member_samples: int, seed: int, device: torch.device):
        if single_member_samples < 0:
            raise ValueError(f"`single_member_samples` must be >= 0. Got {single_member_samples}.")
        self.single_member_samples = single_member_samples
        self.generator = torch.Generator(device=device).manual_seed(seed)
        self.last: dict[str, Tensor] | None = None

    def capture(self, global_cond: Tensor, member0: nn.Module, horizon: int, action_dim: int) -> None:
        """Keep the members' embeddings (B, N, G) and, if asked, member 0's extra chunks."""
        k = self.single_member_samples
        features = {"embedding": global_cond.detach().clone()}  # (B, N, G)
        if k > 0:
            b = global_cond.shape[0]
            chunk = member0.diffusion.conditional_sample(
                b * k, global_cond=global_cond[:, 0].repeat_interleave(k, dim=0), generator=self.generator
            )  # (B*K', T, A)
            features["single_member_samples"] = chunk.view(b, k, horizon, action_dim)
        self.last = features


class FeatureCaptureMixin:
    """The capture's side of :class:`~.modeling_ensemble_diffusion.EnsembleDiffusionPolicy`: switching it on and
    off, and the last prediction's features. Reads the policy's `config`, `members` and `_capture`."""

    def enable_feature_capture(self, single_member_samples: int = 0, seed: int = 0) -> None:
        """Keep, at each prediction, what failure detectors read besides the action samples, in
        `self.last_features` (see `feature_capture`); the actions stay as they are."""
        self._capture = FeatureCapture(single_member_samples, seed, next(self.parameters()).device)

    def disable_feature_capture(self) -> None:
        self._capture = None

    @property
    def last_features(self) -> dict[str, Tensor] | None:
        """The last prediction's captured features (None while capture is off or before a prediction)."""
        return None if self._capture is None else self._capture.last

    def _capture_features(self, global_cond: Tensor) -> None:
        if self._capture is not None:
            self._capture.capture(
                global_cond, self.members[0], self.config.horizon, self.config.action_feature.shape[0]
            )
