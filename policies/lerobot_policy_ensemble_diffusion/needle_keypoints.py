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
"""The auxiliary needle target (`needle_keypoints_weight` > 0): per member a linear head on its image
features that locates the needle's tip, middle and tail in the image. Trained with the members, it makes
their encoders see the needle; it is never an input the policy acts on."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .configuration_ensemble_diffusion import EnsembleDiffusionConfig
from .members import image_encoders


def make_needle_heads(config: EnsembleDiffusionConfig, members: list[nn.Module]) -> nn.ModuleList | None:
    """One head per member, (features of all cameras) -> (needle_keypoints_dim,); None at weight 0."""
    if config.needle_keypoints_weight <= 0:
        return None
    if not config.image_features:
        raise ValueError("`needle_keypoints_weight` > 0 needs an image input; the policy has none.")
    width = image_encoders(members[0])[0].feature_dim * len(config.image_features)
    return nn.ModuleList(nn.Linear(width, config.needle_keypoints_dim) for _ in range(config.n_members))


def needle_keypoint_error(
    head: nn.Module,
    member: nn.Module,
    n: int,
    encoded: list[Tensor],
    target: Tensor,
    n_obs_steps: int,
    batch_size: int,
) -> Tensor:
    """Member `n`'s mean squared error in locating the needle from its features of the current image.

    `encoded`: the outputs of the member's image encoder(s) in this loss, as
    `DiffusionModel._prepare_global_conditioning` makes them: one (B * S * n_cameras, F) from a shared
    encoder, or one (B * S, F) per camera from separate encoders. `target`: (B, D) or (B, S, D).
    """
    n_encoders = len(image_encoders(member))
    if len(encoded) != n_encoders:
        raise RuntimeError(
            f"Expected one pass of each of member {n}'s {n_encoders} image encoder(s), saw {len(encoded)}."
        )
    s = n_obs_steps
    features = torch.cat([out.reshape(batch_size, s, -1) for out in encoded], dim=-1)[:, -1]
    target = target[:, -1] if target.ndim == 3 else target  # (B, S, D) from the dataset: the current step
    predicted = head(features.float())
    return nn.functional.mse_loss(predicted, target.to(predicted.dtype))


def estimate_needle_keypoints(members: nn.ModuleList, heads: nn.ModuleList, images: list[Tensor]) -> Tensor:
    """(B, N, D): each member's estimate of the needle keypoints from the current image of each camera,
    (B, C, H, W) per camera."""
    estimates = []
    for n, member in enumerate(members):
        encoders = image_encoders(member)
        if len(encoders) == 1:
            features = [encoders[0](im) for im in images]
        else:
            features = [encoder(im) for encoder, im in zip(encoders, images, strict=True)]
        estimates.append(heads[n](torch.cat(features, dim=-1)))
    return torch.stack(estimates, dim=1)


@torch.no_grad()
def predict_needle_keypoints(policy, batch: dict[str, Tensor]) -> Tensor:
    """(B, N, D): each member's estimate of the needle keypoints from the current image(s).

    The auxiliary heads of `needle_keypoints_weight` read from the members' image features; this says what the
    encoders see of the needle (`studies/benchmarks/needle_attention.py`). `policy` is an `EnsembleDiffusionPolicy`;
    `batch` a normalized observation, (B, C, H, W) or (B, S, C, H, W) per camera (the last step is read).
    """
    if policy.needle_heads is None:
        raise ValueError(
            "This policy was trained without the auxiliary needle target (`needle_keypoints_weight`=0); it "
            "has no keypoint heads."
        )
    images = [batch[key] for key in policy.config.image_features]
    images = [im[:, -1] if im.ndim == 5 else im for im in images]
    return estimate_needle_keypoints(policy.members, policy.needle_heads, images)
