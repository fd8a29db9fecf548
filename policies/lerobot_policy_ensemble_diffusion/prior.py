"""Randomized prior functions for the ensemble's members (Osband, Aslanides and Cassirer, NeurIPS 2018).

Members trained from different initialisations on the same data agree wherever the data pins the answer
down, but they also tend to agree where it does not: smooth networks extrapolate alike, so a state unlike any
in the training data can leave the ensemble confident. A randomized prior gives each member its own fixed
random function p_n of the observation, added (times `scale`) to the member's network output. Training fits
the trainable part to the data minus the prior, so in distribution the members still agree; away from the
data nothing cancels the priors, and the members differ by as much as their priors do.

Here p_n reads the member's global conditioning (its state and image features, detached so that the
encoder is not trained to flatten it) and outputs one value per predicted step and action dimension, added
to the U-Net's prediction (the denoised sample or the noise, whichever `prediction_type` says) at every
diffusion step. Its weights are frozen at their random initialisation and saved with the member.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

PRIOR_HIDDEN_DIM = 256


class RandomPrior(nn.Module):
    """A frozen random MLP: (B, G) conditioning -> (B, T, A), about unit scale before `scale`.

    Layer norm (no affine) -> Linear -> Mish -> Linear -> Mish -> Linear, weights drawn N(0, 1 / fan_in) from
    the global torch RNG (seed it per member), biases zero.
    """

    def __init__(self, cond_dim: int, horizon: int, action_dim: int, scale: float):
        super().__init__()
        if not (math.isfinite(scale) and scale > 0):
            raise ValueError(f"A random prior needs a finite `scale` > 0. Got {scale}.")
        self.horizon, self.action_dim, self.scale = horizon, action_dim, float(scale)
        sizes = [cond_dim, PRIOR_HIDDEN_DIM, PRIOR_HIDDEN_DIM, horizon * action_dim]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:], strict=True))
        with torch.no_grad():
            for layer in self.layers:
                layer.weight.normal_(0.0, 1.0 / math.sqrt(layer.in_features))
                layer.bias.zero_()
        self.requires_grad_(False)

    def forward(self, global_cond: Tensor) -> Tensor:
        return prior_mlp(global_cond.detach(), self.layers, self.scale, (self.horizon, self.action_dim))


def prior_mlp(
    global_cond: Tensor, layers: Sequence[nn.Module], scale: float, out_shape: tuple[int, int]
) -> Tensor:
    """The prior's function, shared by `RandomPrior` and its fused form: (..., G) -> (..., T, A)."""
    x = nn.functional.layer_norm(global_cond, global_cond.shape[-1:])
    for i, layer in enumerate(layers):
        x = layer(x)
        if i < len(layers) - 1:
            x = nn.functional.mish(x)
    return scale * x.view(*global_cond.shape[:-1], *out_shape)


class UnetWithPrior(nn.Module):
    """A member's U-Net plus its random prior: `unet(x, t, global_cond) + prior(global_cond)`.

    Stands in for `DiffusionModel.unet` (same call), so LeRobot's training loss and sampling loop use it
    unchanged.
    """

    def __init__(self, unet: nn.Module, prior: RandomPrior):
        super().__init__()
        self.unet = unet
        self.prior = prior

    def forward(self, x: Tensor, timestep: Tensor | int, global_cond: Tensor | None = None) -> Tensor:
        return self.unet(x, timestep, global_cond=global_cond) + self.prior(global_cond).to(x.dtype)


def unet_global_cond_dim(unet: nn.Module) -> int:
    """Size of the global conditioning a LeRobot `DiffusionConditionalUnet1d` was built for."""
    film_input = unet.down_modules[0][0].cond_encoder[1].in_features  # [step embedding, global cond]
    return film_input - unet.diffusion_step_encoder[-1].out_features
