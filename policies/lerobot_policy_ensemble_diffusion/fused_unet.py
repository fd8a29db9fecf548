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
"""The members' U-Nets fused into one network: every member layer stacked into one wider layer.

Channels are member-major (member n owns channels [n * C, (n + 1) * C)):

- Conv1d -> one batched GEMM over the members (im2col + `torch.baddbmm`, "gemm" mode, the default) or
  one grouped convolution (`groups = N`, "grouped" mode);
- ConvTranspose1d -> one grouped transposed convolution;
- in "gemm" mode, either of them on a sequence shorter than the kernel taps it reads (the U-Net's inner
  levels: T = 2 and 4 under a 5-tap kernel) -> one batched GEMM with the layer's dense matrix over the
  whole sequence (C_in * T -> C_out * T'), which skips the products with the zero padding and the im2col
  copy: the same sums up to float rounding, in fewer FLOPs (2/3 at T = 2);
- GroupNorm(G, C) -> GroupNorm(N * G, N * C) (groups never straddle two members);
- Linear -> a batched matmul over a member axis (`GroupedLinear`); Mish and FiLM act element-wise.

Why two conv modes, and the timings behind them: `batched_members`' module docstring. Every fused weight is a
frozen copy (no gradients): the members stay the source of truth.
"""

from __future__ import annotations

import copy

import einops
import torch
import torch.nn.functional as F  # noqa: N812
from lerobot.policies.diffusion.modeling_diffusion import (
    DiffusionConditionalResidualBlock1d,
    DiffusionConditionalUnet1d,
    DiffusionConv1dBlock,
)
from torch import Tensor, nn

from .prior import RandomPrior, prior_mlp

CONV_MODES = ("gemm", "grouped")


def unwrap_compiled(module: nn.Module) -> nn.Module:
    """The module behind `torch.compile` (members built with `compile_model=True`)."""
    return getattr(module, "_orig_mod", module)


def _frozen(t: Tensor) -> nn.Parameter:
    return nn.Parameter(t.detach().clone(), requires_grad=False)


class GroupedLinear(nn.Module):
    """N independent linear layers applied along a member axis: (..., N, in) -> (..., N, out)."""

    def __init__(self, linears: list[nn.Linear]):
        super().__init__()
        self.weight = _frozen(torch.stack([lin.weight for lin in linears]))  # (N, out, in)
        self.bias = None if linears[0].bias is None else _frozen(torch.stack([lin.bias for lin in linears]))

    def forward(self, x: Tensor, in_features: slice = slice(None), add_bias: bool = True) -> Tensor:
        """x: (..., N, in) -> (..., N, out).

        `in_features` restricts the product to a slice of the input features (x then holds only those):
        W x = W[:, a] x_a + W[:, b] x_b, which lets a constant part of the input be multiplied once.
        """
        lead, (n, d_in) = x.shape[:-2], x.shape[-2:]
        x = x.reshape(-1, n, d_in).transpose(0, 1)  # (N, M, in)
        w = self.weight[:, :, in_features].transpose(1, 2)  # (N, in, out)
        if self.bias is None or not add_bias:
            y = torch.bmm(x, w)  # (N, M, out)
        else:
            y = torch.baddbmm(self.bias.unsqueeze(1), x, w)  # (N, M, out)
        return y.transpose(0, 1).reshape(*lead, n, -1)


class FusedRandomPrior(nn.Module):
    """N members' `RandomPrior`s as one: (M, N, G) conditioning -> (M, N, T, A)."""

    def __init__(self, priors: list[RandomPrior]):
        super().__init__()
        p0 = priors[0]
        self.horizon, self.action_dim, self.scale = p0.horizon, p0.action_dim, p0.scale
        if any(p.scale != self.scale for p in priors):
            raise ValueError(f"Members' priors must share one scale. Got {[p.scale for p in priors]}.")
        self.layers = nn.ModuleList(
            GroupedLinear([p.layers[i] for p in priors]) for i in range(len(p0.layers))
        )

    def forward(self, global_cond: Tensor) -> Tensor:
        return prior_mlp(global_cond, self.layers, self.scale, (self.horizon, self.action_dim))


class FusedConv1d(nn.Module):
    """N `nn.Conv1d` (or `nn.ConvTranspose1d`) on member-major channels: (B, N*C_in, T) -> (B, N*C_out, T')."""

    def __init__(self, convs: list[nn.Module], mode: str):
        super().__init__()
        c0 = convs[0]
        if mode not in CONV_MODES:
            raise ValueError(f"`mode` must be one of {list(CONV_MODES)}. Got {mode!r}.")
        self.n = len(convs)
        self.transposed = isinstance(c0, nn.ConvTranspose1d)
        self.in_channels, self.out_channels = c0.in_channels, c0.out_channels
        self.kernel_size, self.stride, self.padding = c0.kernel_size[0], c0.stride[0], c0.padding[0]
        self.dilation = c0.dilation[0]
        self.output_padding = c0.output_padding[0] if self.transposed else 0
        gemm_ok = not self.transposed and c0.groups == 1 and self.dilation == 1 and c0.padding_mode == "zeros"
        self.mode = mode if gemm_ok else "grouped"
        self.groups = c0.groups * self.n
        # Conv weight (C_out, C_in / g, k) and transposed-conv weight (C_in, C_out / g, k): the member axis is
        # the first one in both layouts.
        self.weight = _frozen(torch.cat([c.weight for c in convs]))
        self.bias = None if c0.bias is None else _frozen(torch.cat([c.bias for c in convs]))
        self._trimmed: dict[int, tuple[int, int, Tensor]] = {}
        self._dense: dict[int, tuple[Tensor, Tensor | None] | None] = {}
        self._dense_ok = mode == "gemm" and c0.groups == 1

    def forward(self, x: Tensor) -> Tensor:
        dense = self._dense_matrix(x) if self._dense_ok else None
        if dense is not None:
            weight, bias = dense  # (N, C_in*T, C_out*T'), (N, 1, C_out*T') or None
            b, n = x.shape[0], self.n
            rows = x.reshape(b, n, -1).transpose(0, 1)  # (N, B, C_in*T), a view
            y = torch.bmm(rows, weight) if bias is None else torch.baddbmm(bias, rows, weight)
            return y.transpose(0, 1).reshape(b, n * self.out_channels, -1)
        if self.transposed:
            return F.conv_transpose1d(
                x, self.weight, self.bias, self.stride, self.padding, self.output_padding, self.groups
            )
        if self.mode == "grouped":
            return F.conv1d(x, self.weight, self.bias, self.stride, self.padding, groups=self.groups)
        n, c_in, c_out = self.n, self.in_channels, self.out_channels
        b, t_in = x.shape[0], x.shape[-1]
        left, k, weight = self._gemm_weight(t_in)  # (N, C_in*k, C_out) over the taps that see the input
        t_out = (t_in + 2 * self.padding - self.kernel_size) // self.stride + 1
        right = max(0, (t_out - 1) * self.stride + k - left - t_in)  # the last window must fit
        if left or right:
            x = F.pad(x, (left, right))
        cols = x.reshape(b, n, c_in, -1).unfold(-1, k, self.stride)[:, :, :, :t_out]  # (B, N, C_in, T', k)
        cols = cols.permute(1, 0, 3, 2, 4).reshape(n, b * t_out, c_in * k)  # (N, B*T', C_in*k)
        if self.bias is None:
            y = torch.bmm(cols, weight)
        else:
            y = torch.baddbmm(self.bias.view(n, 1, c_out), cols, weight)  # (N, B*T', C_out)
        return y.view(n, b, t_out, c_out).permute(1, 0, 3, 2).reshape(b, n * c_out, t_out)

    def _output_length(self, t_in: int) -> int:
        k, s, p, d = self.kernel_size, self.stride, self.padding, self.dilation
        if self.transposed:
            return (t_in - 1) * s - 2 * p + d * (k - 1) + self.output_padding + 1
        return (t_in + 2 * p - d * (k - 1) - 1) // s + 1

    def _dense_matrix(self, x: Tensor) -> tuple[Tensor, Tensor | None] | None:
        """The layer as a dense map of the whole sequence, when that is cheaper than im2col (cached per T).

        Worth it when the input is shorter than the taps each output reads (a conv on T = 2 with 3 taps
        that see data, a transposed conv on T <= k / stride): the dense GEMM does C_in*T x C_out*T' products
        per row against T' x taps x C_in x C_out. Its entries are the kernel's weights, read off by running
        the layer on the identity (each output then holds one weight times 1: exact).
        """
        t_in = x.shape[-1]
        if t_in in self._dense:
            return self._dense[t_in]
        k, s = self.kernel_size, self.stride
        if self.transposed:
            taps = -(-k // s)
        else:
            _, taps, _ = self._gemm_weight(t_in)
        dense = None
        if t_in < taps or (self.transposed and t_in <= taps):
            n, c_in, c_out = self.n, self.in_channels, self.out_channels
            t_out = self._output_length(t_in)
            eye = torch.eye(c_in * t_in, dtype=x.dtype, device=x.device).view(c_in * t_in, c_in, t_in)
            per_member = []
            for m in range(n):
                if self.transposed:
                    w = self.weight[m * c_in : (m + 1) * c_in]  # (C_in, C_out, k)
                    out = F.conv_transpose1d(
                        eye, w, None, s, self.padding, self.output_padding, 1, self.dilation
                    )
                else:
                    w = self.weight[m * c_out : (m + 1) * c_out]  # (C_out, C_in, k)
                    out = F.conv1d(eye, w, None, s, self.padding, self.dilation)
                per_member.append(out.reshape(c_in * t_in, c_out * t_out))  # (C_in*T, C_out*T')
            weight = torch.stack(per_member).to(self.weight.dtype)
            bias = None
            if self.bias is not None:
                bias = self.bias.view(n, c_out, 1).expand(n, c_out, t_out).reshape(n, 1, c_out * t_out)
            dense = (weight, bias)
        self._dense[t_in] = dense
        return dense

    def _gemm_weight(self, t_in: int) -> tuple[int, int, Tensor]:
        """Left padding, kernel taps and GEMM weight (N, C_in*taps, C_out) for an input of length `t_in`.

        On short inputs the outer kernel taps only ever meet the zero padding (e.g. k = 5, padding 2 on
        T = 2: taps 0 and 4); they are left out, exactly, which saves reading their weights. The trimmed
        weight is cached per input length.
        """
        k, p, s = self.kernel_size, self.padding, self.stride
        t_out = (t_in + 2 * p - k) // s + 1
        first = max(0, p - (t_out - 1) * s)  # output t reads input t*s - p + j for tap j
        last = min(k - 1, p + t_in - 1)
        n, c_in, c_out = self.n, self.in_channels, self.out_channels
        if first == 0 and last == k - 1:
            return p, k, self.weight.view(n, c_out, c_in * k).transpose(1, 2)
        if t_in not in self._trimmed:
            taps = last - first + 1
            trimmed = self.weight.view(n, c_out, c_in, k)[..., first : last + 1]  # (N, C_out, C_in, taps)
            trimmed = trimmed.reshape(n, c_out, c_in * taps)  # contiguous copy
            self._trimmed[t_in] = (p - first, taps, trimmed.transpose(1, 2))
        return self._trimmed[t_in]


class FusedGroupNorm(nn.Module):
    """N `nn.GroupNorm(G, C)` as one GroupNorm(N * G, N * C) on member-major channels."""

    def __init__(self, norms: list[nn.GroupNorm]):
        super().__init__()
        g0 = norms[0]
        self.num_groups = g0.num_groups * len(norms)
        self.eps = g0.eps
        self.weight = _frozen(torch.cat([g.weight for g in norms])) if g0.affine else None
        self.bias = _frozen(torch.cat([g.bias for g in norms])) if g0.affine else None

    def forward(self, x: Tensor) -> Tensor:
        return F.group_norm(x, self.num_groups, self.weight, self.bias, self.eps)


def _fuse_leaf(modules: list[nn.Module], conv_mode: str) -> nn.Module:
    m0 = modules[0]
    if any(type(m) is not type(m0) for m in modules):
        raise ValueError(
            f"Cannot fuse modules of different types: {sorted({type(m).__name__ for m in modules})}."
        )
    if isinstance(m0, (nn.Conv1d, nn.ConvTranspose1d)):
        return FusedConv1d(modules, conv_mode)
    if isinstance(m0, nn.GroupNorm):
        return FusedGroupNorm(modules)
    if isinstance(m0, (nn.Mish, nn.Identity)):
        return copy.deepcopy(m0)
    raise TypeError(f"Don't know how to fuse a {type(m0).__name__}.")


def _cat_members(x: Tensor, skip: Tensor, n: int) -> Tensor:
    """Per-member channel concatenation: (B, N*C1, T), (B, N*C2, T) -> (B, N*(C1+C2), T)."""
    b, _, t = x.shape
    return torch.cat([x.view(b, n, -1, t), skip.view(b, n, -1, t)], dim=2).view(b, -1, t)


class FusedConv1dBlock(nn.Module):
    """Fused `DiffusionConv1dBlock`s: Conv1d -> GroupNorm -> Mish on member-major channels."""

    def __init__(self, blocks: list[DiffusionConv1dBlock], conv_mode: str):
        super().__init__()
        self.conv = _fuse_leaf([b.block[0] for b in blocks], conv_mode)
        self.norm = _fuse_leaf([b.block[1] for b in blocks], conv_mode)

    def forward(self, x: Tensor) -> Tensor:
        return F.mish(self.norm(self.conv(x)))


class FusedResidualBlock1d(nn.Module):
    """Fused `DiffusionConditionalResidualBlock1d`s with per-member FiLM conditioning."""

    def __init__(self, blocks: list[DiffusionConditionalResidualBlock1d], conv_mode: str):
        super().__init__()
        b0 = blocks[0]
        self.out_channels = b0.out_channels
        self.use_film_scale_modulation = b0.use_film_scale_modulation
        self.conv1 = FusedConv1dBlock([b.conv1 for b in blocks], conv_mode)
        self.conv2 = FusedConv1dBlock([b.conv2 for b in blocks], conv_mode)
        self.cond_encoder = GroupedLinear([b.cond_encoder[1] for b in blocks])  # after the shared Mish
        self.residual_conv = _fuse_leaf([b.residual_conv for b in blocks], conv_mode)

    def film(self, mish_cond: Tensor) -> Tensor:
        """The FiLM embedding of the conditioning (after the Mish opening each member's cond encoder).

        (B, N, cond_dim) -> (B, N, C) or (B, N, 2C).
        """
        return self.cond_encoder(mish_cond)

    def forward(self, x: Tensor, cond_embed: Tensor) -> Tensor:
        """
        Args:
            x: (B, N * in_channels, T)
            cond_embed: (B, N, C) or (B, N, 2C) FiLM embedding from `film`.
        Returns:
            (B, N * out_channels, T)
        """
        out = self.conv1(x)  # (B, N*C, T)
        b = cond_embed.shape[0]
        if self.use_film_scale_modulation:
            scale = cond_embed[..., : self.out_channels].reshape(b, -1, 1)  # (B, N*C, 1)
            bias = cond_embed[..., self.out_channels :].reshape(b, -1, 1)  # (B, N*C, 1)
            out = torch.addcmul(bias, scale, out)
        else:
            out = out + cond_embed.reshape(b, -1, 1)
        out = self.conv2(out)
        return out + self.residual_conv(x)


class FusedUnet1d(nn.Module):
    """Fused `DiffusionConditionalUnet1d`s: one forward pass evaluates every member."""

    def __init__(self, unets: list[DiffusionConditionalUnet1d], conv_mode: str):
        super().__init__()
        self.n = len(unets)
        u0 = unets[0]
        self.step_embedding = copy.deepcopy(u0.diffusion_step_encoder[0])  # sinusoidal, parameter-free
        self.step_linear1 = GroupedLinear([u.diffusion_step_encoder[1] for u in unets])
        self.step_linear2 = GroupedLinear([u.diffusion_step_encoder[3] for u in unets])

        def res(blocks):
            return FusedResidualBlock1d(blocks, conv_mode)

        def stage(modules):
            return nn.ModuleList(
                [
                    res([m[0] for m in modules]),
                    res([m[1] for m in modules]),
                    _fuse_leaf([m[2] for m in modules], conv_mode),
                ]
            )

        self.down = nn.ModuleList(
            stage([u.down_modules[i] for u in unets]) for i in range(len(u0.down_modules))
        )
        self.mid = nn.ModuleList(res([u.mid_modules[i] for u in unets]) for i in range(len(u0.mid_modules)))
        self.up = nn.ModuleList(stage([u.up_modules[i] for u in unets]) for i in range(len(u0.up_modules)))
        self.final_block = FusedConv1dBlock([u.final_conv[0] for u in unets], conv_mode)
        self.final_conv = _fuse_leaf([u.final_conv[1] for u in unets], conv_mode)

    def res_blocks(self) -> list[FusedResidualBlock1d]:
        """The residual blocks in the order `denoise` consumes their FiLM embeddings."""
        blocks = [blk for stage in self.down for blk in stage[:2]]
        blocks += list(self.mid)
        blocks += [blk for stage in self.up for blk in stage[:2]]
        return blocks

    def step_embedding_mish(self, timestep: Tensor) -> Tensor:
        """Mish of every member's diffusion-step embedding: (B,) -> (B, N, E)."""
        emb = self.step_embedding(timestep)  # (B, E)
        emb = emb.unsqueeze(1).expand(-1, self.n, -1)  # (B, N, E)
        return F.mish(self.step_linear2(F.mish(self.step_linear1(emb))))  # (B, N, E)

    def film_embeddings(self, timestep: Tensor, global_cond: Tensor) -> list[Tensor]:
        """Every residual block's FiLM embedding, as the members compute it: list of (B, N, C or 2C)."""
        mish_cond = torch.cat(
            [self.step_embedding_mish(timestep), F.mish(global_cond)], dim=-1
        )  # (B, N, E+G)
        return [blk.film(mish_cond) for blk in self.res_blocks()]

    def observation_films(self, global_cond: Tensor) -> list[Tensor]:
        """The observation part of every block's FiLM embedding.

        FiLM = W Mish([e_t, g]) + b = (W_g Mish(g) + b) + W_t Mish(e_t) (Mish acts element-wise): the
        observation part is computed once per chunk, the diffusion-step part once per step (`step_films`).

        Args:
            global_cond: (B, N, G)
        Returns:
            list of (B, N, C or 2C), one per residual block.
        """
        e = self.step_linear2.weight.shape[1]
        mish_g = F.mish(global_cond)  # (B, N, G)
        return [blk.cond_encoder(mish_g, in_features=slice(e, None)) for blk in self.res_blocks()]

    def step_films(self, timestep: Tensor) -> list[Tensor]:
        """The diffusion-step part of every block's FiLM: (1,) -> list of (1, N, C or 2C)."""
        e = self.step_linear2.weight.shape[1]
        mish_t = self.step_embedding_mish(timestep)  # (1, N, E)
        return [
            blk.cond_encoder(mish_t, in_features=slice(0, e), add_bias=False) for blk in self.res_blocks()
        ]

    def denoise(self, x: Tensor, films: list[Tensor]) -> Tensor:
        """
        Args:
            x: (B, N, T, A) every member's noisy action chunk.
            films: every residual block's FiLM embedding (B or 1, N, C or 2C), in `res_blocks` order.
        Returns:
            (B, N, T, A) every member's prediction.
        """
        n = self.n
        x = einops.rearrange(x, "b n t a -> b (n a) t")
        films = iter(films)
        skips = []
        for res1, res2, downsample in self.down:
            x = res2(res1(x, next(films)), next(films))
            skips.append(x)
            x = downsample(x)
        for res in self.mid:
            x = res(x, next(films))
        for res1, res2, upsample in self.up:
            x = _cat_members(x, skips.pop(), n)
            x = upsample(res2(res1(x, next(films)), next(films)))
        x = self.final_conv(self.final_block(x))  # (B, N*A, T)
        return einops.rearrange(x, "b (n a) t -> b n t a", n=n)

    def forward(self, x: Tensor, timestep: Tensor, global_cond: Tensor) -> Tensor:
        """
        Args:
            x: (B, N, T, A) every member's noisy action chunk.
            timestep: (B,) diffusion step, shared by the members.
            global_cond: (B, N, G) every member's observation encoding.
        Returns:
            (B, N, T, A) every member's prediction.
        """
        return self.denoise(x, self.film_embeddings(timestep, global_cond))
