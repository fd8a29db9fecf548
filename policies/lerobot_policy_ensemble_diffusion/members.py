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
"""The ensemble's members: LeRobot `DiffusionPolicy` modules with an optional random prior and an image
backbone cut to fewer ResNet stages, their image encoders, and the per-member training helpers (the
bootstrap resample, the encoders' outputs for the auxiliary needle loss)."""

from __future__ import annotations

from contextlib import contextmanager

import torch
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy, SpatialSoftmax
from torch import Tensor, nn

from .configuration_ensemble_diffusion import EnsembleDiffusionConfig
from .prior import RandomPrior, UnetWithPrior, unet_global_cond_dim


def make_member(config: EnsembleDiffusionConfig) -> DiffusionPolicy:
    """One LeRobot `DiffusionPolicy` of the ensemble, its image backbone cut to `vision_backbone_stages`, with
    its random prior when `prior_scale` > 0."""
    member = DiffusionPolicy(config.member_config())
    if config.prior_scale > 0:
        unet = member.diffusion.unet
        prior = RandomPrior(
            unet_global_cond_dim(getattr(unet, "_orig_mod", unet)),
            config.horizon,
            config.action_feature.shape[0],
            config.prior_scale,
        )
        member.diffusion.unet = UnetWithPrior(unet, prior)
    if config.image_features and config.vision_backbone_stages < 4:
        # The encoder sees the image after its resize and crop, as in LeRobot's own dry run.
        image_shape = next(iter(config.image_features.values())).shape
        height_width = config.crop_shape or config.resize_shape or image_shape[1:]
        for encoder in image_encoders(member):
            cut_image_backbone(
                encoder,
                config.vision_backbone_stages,
                (1, image_shape[0], *height_width),
                config.spatial_softmax_num_keypoints,
            )
    return member


def cut_image_backbone(
    encoder: nn.Module, stages: int, input_shape: tuple[int, ...], num_keypoints: int
) -> None:
    """Keep a LeRobot `DiffusionRgbEncoder`'s ResNet backbone up to stage `stages` and rebuild its spatial
    softmax for the finer feature map (same number of keypoints, so the encoder's output is unchanged)."""
    # LeRobot's backbone is the ResNet's children up to layer4: conv1, norm, relu, maxpool, layer1..layer4.
    encoder.backbone = nn.Sequential(*list(encoder.backbone.children())[: 4 + stages])
    with torch.no_grad():
        feature_map_shape = tuple(encoder.backbone(torch.zeros(input_shape)).shape[1:])
    encoder.pool = SpatialSoftmax(feature_map_shape, num_kp=num_keypoints)


def image_encoders(member: DiffusionPolicy) -> list[nn.Module]:
    """A member's image encoder(s): one shared by the cameras, or one per camera."""
    encoder = member.diffusion.rgb_encoder
    return list(encoder) if isinstance(encoder, nn.ModuleList) else [encoder]


@contextmanager
def captured_outputs(modules: list[nn.Module]):
    """Collect the outputs of `modules`, in call order, while the context is open (forward hooks)."""
    outputs: list[Tensor] = []
    handles = [m.register_forward_hook(lambda _m, _args, out: outputs.append(out)) for m in modules]
    try:
        yield outputs
    finally:
        for handle in handles:
            handle.remove()


def bootstrap_batch(batch: dict, index: Tensor, batch_size: int) -> dict:
    """Rows `index` of every per-sample entry of `batch` (tensors and lists with `batch_size` rows)."""
    out = {}
    for key, value in batch.items():
        if isinstance(value, Tensor) and value.ndim > 0 and value.shape[0] == batch_size:
            out[key] = value[index]
        elif isinstance(value, list) and len(value) == batch_size:
            out[key] = [value[i] for i in index.tolist()]
        else:
            out[key] = value
    return out
