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
"""N LeRobot `DiffusionModel`s evaluated as one network for inference.

The U-Net (run once per denoising step, so it dominates the cost) is fused into one network whose layers
stack every member's (`fused_unet`: Conv1d as one batched GEMM, "gemm" mode, or one grouped convolution,
"grouped" mode; GroupNorm, Linear and FiLM per member along a member axis).

So a denoising step is one pass of about 150 kernels for the whole ensemble instead of N passes, and the
scheduler steps all members at once. On a CPU at batch 1 the members' own Conv1d calls (PyTorch's generic
CPU convolution on T = 2 to 8 time steps) cost several times a GEMM over the same weights, which is why the
"gemm" mode exists; what remains is bound by reading the N members' weights once per step. On an H100 the
grouped convolution is slow too (cuDNN's grouped kernels on T <= 8): with the paper preset's U-Net a fused
denoising step took 14.9 ms grouped and 4.3 ms as GEMMs, against 4.6 ms for one member's own U-Net. The image
encoders are ResNets: there the members run one after another (their own modules, no copy) on images
resized / centre-cropped once, and on a CPU the convolutions of the last stage, which see only a few output
positions, run as GEMMs too (`SmallMapConv2d`). The FiLM conditioning W Mish([e_t, g]) + b is split into
its observation part (computed once per chunk) and its diffusion-step part (cached per step).

The fused copy of the U-Net weights is built from the members' current weights, without gradients, and is
used only for inference; the members stay the source of truth (training, state dict, checkpoints).
"""

from __future__ import annotations

import copy

import einops
import torch
import torch.nn.functional as F  # noqa: N812
from lerobot.policies.diffusion.modeling_diffusion import DiffusionModel, DiffusionRgbEncoder
from lerobot.utils.constants import OBS_ENV_STATE, OBS_IMAGES, OBS_STATE
from torch import Tensor, nn

from .fused_unet import FusedRandomPrior, FusedUnet1d, unwrap_compiled
from .prior import UnetWithPrior
from .rtc_inpainting import inpaint_model_output


class SmallMapConv2d(nn.Module):
    """A member's `nn.Conv2d` (same weight tensor, no copy) that runs as im2col + GEMM on small outputs.

    ResNet's last stage on a 2x2 or 3x3 map (64 or 72 px images) has 2.4M weights per 3x3 convolution and
    only a few output positions; on a CPU PyTorch's convolution then costs markedly more than one GEMM over
    the same weights (5 members of the CPU preset at 72 px, batch 1: 0.34 s with the convolution, 0.26 s
    with the GEMM, measured). Larger outputs (compute-bound) use the convolution.
    """

    def __init__(self, conv: nn.Conv2d, max_positions: int):
        super().__init__()
        self.conv = conv
        self.max_positions = max_positions

    def forward(self, x: Tensor) -> Tensor:
        c = self.conv
        b, _, h, w = x.shape
        h_out = (h + 2 * c.padding[0] - c.dilation[0] * (c.kernel_size[0] - 1) - 1) // c.stride[0] + 1
        w_out = (w + 2 * c.padding[1] - c.dilation[1] * (c.kernel_size[1] - 1) - 1) // c.stride[1] + 1
        if h_out * w_out > self.max_positions or c.groups != 1 or c.padding_mode != "zeros":
            return c(x)
        cols = F.unfold(x, c.kernel_size, c.dilation, c.padding, c.stride)  # (B, C_in*kh*kw, L)
        y = F.linear(cols.transpose(1, 2), c.weight.view(c.out_channels, -1), c.bias)  # (B, L, C_out)
        return y.transpose(1, 2).reshape(b, c.out_channels, h_out, w_out)


def _small_map_view(module: nn.Module, max_positions: int) -> nn.Module:
    """`module` with every Conv2d wrapped in `SmallMapConv2d`; shares all parameters with `module`."""
    if isinstance(module, nn.Conv2d):
        return SmallMapConv2d(module, max_positions)
    if not module._modules:
        return module
    view = copy.copy(module)  # shallow: same forward, parameters and buffers; new child table below
    view._modules = {
        name: None if child is None else _small_map_view(child, max_positions)
        for name, child in module._modules.items()
    }
    return view


class SharedPreprocessEncoders:
    """The members' own `DiffusionRgbEncoder`s (one camera) with the resize and centre crop run once.

    The encoders' early stages are compute-bound, so the members run one after another on the shared
    preprocessed images, reading the members' own weights (nothing is copied). In "gemm" mode the
    convolutions with at most `SMALL_MAP_POSITIONS` output positions run as GEMMs (`SmallMapConv2d`).
    Deliberately no `nn.Module`: it only refers to the members' modules.
    """

    SMALL_MAP_POSITIONS = 9  # up to ResNet's 3x3 last-stage map of a 72 px image

    def __init__(self, encoders: list[DiffusionRgbEncoder], conv_mode: str):
        self.encoders = encoders
        self.backbones = [
            _small_map_view(e.backbone, self.SMALL_MAP_POSITIONS) if conv_mode == "gemm" else e.backbone
            for e in encoders
        ]

    def __call__(self, x: Tensor) -> Tensor:
        """
        Args:
            x: (M, C, H, W) images, normalized as for the members.
        Returns:
            (M, N, D) every member's image feature.
        """
        e0 = self.encoders[0]
        if e0.resize is not None:
            x = e0.resize(x)
        if e0.do_crop:
            x = e0.center_crop(x)  # inference: always the centre crop, as the members in eval mode
        features = []
        for enc, backbone in zip(self.encoders, self.backbones, strict=True):
            f = torch.flatten(enc.pool(backbone(x)), start_dim=1)  # (M, 2K)
            features.append(enc.relu(enc.out(f)))  # (M, D)
        return torch.stack(features, dim=1)  # (M, N, D)


class FusedDiffusionEnsemble(nn.Module):
    """N LeRobot `DiffusionModel`s evaluated as one network (inference only).

    `sample` returns the same chunks as looping `DiffusionModel.conditional_sample` over the members with the
    same initial noise, up to float rounding, for deterministic schedulers (DDIM). With DDPM the per-step
    noise is drawn once for all members, so the draws (not their distribution) differ from the loop's.

    Args:
        models: the members' `DiffusionModel`s (same config).
        conv_mode: "gemm" (default) or "grouped" (see module docstring).
    """

    def __init__(self, models: list[DiffusionModel], conv_mode: str = "gemm"):
        super().__init__()
        if len(models) < 2:
            raise ValueError(f"Fusing needs at least 2 members. Got {len(models)}.")
        config = models[0].config
        self.config = config
        self.n = len(models)
        self.num_inference_steps = models[0].num_inference_steps
        self.noise_scheduler = copy.deepcopy(models[0].noise_scheduler)
        self.image_keys = list(config.image_features)
        self.encoders: list[SharedPreprocessEncoders] = []
        if config.image_features:
            if config.use_separate_rgb_encoder_per_camera:
                self.encoders = [
                    SharedPreprocessEncoders([m.rgb_encoder[c] for m in models], conv_mode)
                    for c in range(len(self.image_keys))
                ]
            else:
                self.encoders = [SharedPreprocessEncoders([m.rgb_encoder for m in models], conv_mode)]
        unets = [unwrap_compiled(m.unet) for m in models]
        self.prior: FusedRandomPrior | None = None
        if isinstance(unets[0], UnetWithPrior):
            self.prior = FusedRandomPrior([u.prior for u in unets])
            unets = [unwrap_compiled(u.unet) for u in unets]
        self.unet = FusedUnet1d(unets, conv_mode)
        self._step_film_cache: dict[tuple[int, torch.device], list[Tensor]] = {}
        self.eval()

    def encode(self, batch: dict[str, Tensor]) -> Tensor:
        """Every member's global conditioning, as `DiffusionModel._prepare_global_conditioning`.

        Args:
            batch: "observation.state" (B, S, state_dim); "observation.images" (B, S, n_cameras, C, H, W)
                and/or "observation.environment_state" (B, S, env_dim).
        Returns:
            (B, N, G) with G = S * (state_dim + n_cameras * D + env_dim).
        """
        n = self.n
        state = batch[OBS_STATE]
        b, s = state.shape[:2]
        feats = [state.unsqueeze(2).expand(b, s, n, state.shape[-1])]  # (B, S, N, state_dim)
        if self.image_keys:
            images = batch[OBS_IMAGES]  # (B, S, n_cameras, C, H, W)
            if len(self.encoders) == len(self.image_keys):  # one encoder per camera
                per_camera = [enc(images[:, :, c].flatten(0, 1)) for c, enc in enumerate(self.encoders)]
            else:
                all_cams = self.encoders[0](einops.rearrange(images, "b s c ... -> (b s c) ..."))
                per_camera = list(einops.rearrange(all_cams, "(bs c) n d -> c bs n d", c=images.shape[2]))
            img = torch.cat(per_camera, dim=-1)  # (B*S, N, n_cameras*D)
            feats.append(img.view(b, s, n, -1))
        if self.config.env_state_feature:
            env = batch[OBS_ENV_STATE]
            feats.append(env.unsqueeze(2).expand(b, s, n, env.shape[-1]))
        cond = torch.cat(feats, dim=-1)  # (B, S, N, F)
        return cond.transpose(1, 2).reshape(b, n, -1)  # (B, N, S*F)

    def sample(
        self,
        global_cond: Tensor,
        samples_per_member: int = 1,
        noise: Tensor | None = None,
        generator: torch.Generator | None = None,
        prefix: Tensor | None = None,
        first_step: int = 0,
    ) -> Tensor:
        """Run the reverse diffusion for every member at once.

        Args:
            global_cond: (B, N, G) from `encode`.
            samples_per_member: K chunks per member, each from its own initial noise.
            noise: optional (B, N, K, T, A) initial noise.
            generator: optional RNG for the initial and the per-step scheduler noise.
            prefix: optional (L, A) committed actions every chunk starts with at step `first_step`
                (real-time chunking, `rtc_inpainting`).
        Returns:
            (B, N, K, T, A) samples, T = horizon.
        """
        b, n, _ = global_cond.shape
        k = samples_per_member
        t_len, a = self.config.horizon, self.config.action_feature.shape[0]
        if noise is None:
            noise = torch.randn(
                (b, n, k, t_len, a), dtype=global_cond.dtype, device=global_cond.device, generator=generator
            )
        sample = noise.permute(0, 2, 1, 3, 4).reshape(b * k, n, t_len, a)  # (B*K, N, T, A), row b*K + k
        cond = global_cond.repeat_interleave(k, dim=0)  # (B*K, N, G)
        observation_films = self.unet.observation_films(cond)  # per block (B*K, N, C or 2C), once per chunk
        prior = None if self.prior is None else self.prior(cond).to(sample.dtype)  # (B*K, N, T, A)
        self.noise_scheduler.set_timesteps(self.num_inference_steps)
        for t in self.noise_scheduler.timesteps:
            step_films = self._step_films(int(t), sample.device)  # per block (1, N, C or 2C), cached
            films = [obs + step for obs, step in zip(observation_films, step_films, strict=True)]
            model_output = self.unet.denoise(sample, films)  # (B*K, N, T, A)
            if prior is not None:
                model_output = model_output + prior
            if prefix is not None:
                model_output = inpaint_model_output(
                    model_output, sample, int(t), self.noise_scheduler, prefix, first_step
                )
            sample = self.noise_scheduler.step(model_output, t, sample, generator=generator).prev_sample
        return sample.view(b, k, n, t_len, a).transpose(1, 2)  # (B, N, K, T, A)

    def _step_films(self, t: int, device: torch.device) -> list[Tensor]:
        """The diffusion-step FiLM parts for step `t`; they depend on the weights only, so they are cached."""
        key = (t, device)
        if key not in self._step_film_cache:
            self._step_film_cache[key] = self.unet.step_films(
                torch.full((1,), t, dtype=torch.long, device=device)
            )
        return self._step_film_cache[key]
