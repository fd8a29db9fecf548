"""Real-time chunking for the ensemble: each member's sampling inpaints the committed prefix. Pure torch.

LeRobot's real-time chunking engine (``lerobot-rollout --inference.type=rtc``) predicts the next chunk in a
background thread while the current one executes. It hands the policy what is left of the current chunk
(``prev_chunk_left_over``, normalized actions from the next one to execute on, zero-padded to the engine's
``execution_horizon``) and the inference delay ``d`` in control steps: the first ``d`` of those actions will
execute while the new chunk is computed, so the new chunk's first ``d`` steps are committed already.

The method: inpainting of that committed prefix in the denoised estimate, at every sampler step. Each step's
model output is turned into the clean chunk it predicts (``x0``); its first ``d`` steps are replaced by the
committed actions, and the output is turned back (``epsilon`` or ``sample``, as the scheduler predicts), so
that the scheduler's step moves the noisy chunk towards a clean chunk that starts with the prefix. The
convolutional U-Net sees that prefix, noised to the step's level, at the next step, and the free part of the
chunk is sampled conditioned on it. At the last step the noise level is zero and the chunk's first ``d``
steps equal the committed actions exactly, in every member and sample, so their mean does too.

Why not RTC's guidance: it needs a vector-Jacobian product through the U-Net at every step (about twice the
cost), written for flow matching; inpainting costs nothing, and on the committed steps it is exact. Only the
committed steps are inpainted (not RTC's soft schedule over the execution horizon). Every member and sample
continues the same prefix, so they disagree less in the steps just after it than from scratch: the policy's
``rtc_score`` chooses whether the gate reads that damped score or a second, free prediction's.
"""

from __future__ import annotations

import torch
from torch import Tensor


def committed_prefix(prev_chunk_left_over: Tensor | None, inference_delay: int) -> Tensor | None:
    """The actions that execute during the inference delay, (L, A) with L <= ``inference_delay``, or None.

    Args:
        prev_chunk_left_over: (S, A) or (1, S, A) normalized actions left of the current chunk, zero-padded at
            the end by the engine (a row of exact zeros in every dimension is padding, not an action).
        inference_delay: control steps (>= 0) the new chunk takes to arrive.
    """
    if prev_chunk_left_over is None or inference_delay <= 0:
        return None
    prev = prev_chunk_left_over
    if prev.ndim == 3:
        if prev.shape[0] != 1:
            raise ValueError(f"`prev_chunk_left_over` must be (S, A) or (1, S, A). Got {tuple(prev.shape)}.")
        prev = prev[0]
    if prev.ndim != 2:
        raise ValueError(f"`prev_chunk_left_over` must be (S, A) or (1, S, A). Got {tuple(prev.shape)}.")
    rows = torch.nonzero(prev.abs().sum(dim=-1) > 0).flatten()
    length = 0 if rows.numel() == 0 else int(rows.max()) + 1
    length = min(length, int(inference_delay))
    return prev[:length] if length > 0 else None


def _alphas(scheduler, t: int, like: Tensor) -> tuple[Tensor, Tensor]:
    alpha_bar = scheduler.alphas_cumprod[int(t)].to(device=like.device, dtype=like.dtype)
    return alpha_bar.sqrt(), (1.0 - alpha_bar).sqrt()


def inpaint_model_output(
    model_output: Tensor, sample: Tensor, t: int, scheduler, prefix: Tensor, first_step: int
) -> Tensor:
    """The model output of one sampler step with the committed prefix written into its clean estimate.

    Args:
        model_output: (..., T, A) what the network predicted at step ``t``, of the scheduler's
            ``prediction_type`` (``epsilon`` or ``sample``).
        sample: (..., T, A) the noisy chunk the network saw at step ``t``.
        t: the diffusion timestep.
        scheduler: a diffusers DDPM or DDIM scheduler (``alphas_cumprod``, ``config.prediction_type``).
        prefix: (L, A) the committed actions.
        first_step: the chunk index of the prefix's first action (the policy's ``n_obs_steps - 1``).

    Returns:
        (..., T, A), the model output whose clean estimate holds ``prefix`` at steps
        ``first_step .. first_step + L - 1``.
    """
    kind = scheduler.config.prediction_type
    if kind not in ("epsilon", "sample"):
        raise ValueError(f"Real-time chunking supports prediction_type 'epsilon' or 'sample'. Got {kind!r}.")
    steps = slice(first_step, first_step + prefix.shape[0])
    if steps.stop > sample.shape[-2]:
        raise ValueError(f"The prefix ({prefix.shape[0]} steps from {first_step}) exceeds the horizon.")
    prefix = prefix.to(device=sample.device, dtype=sample.dtype)
    if kind == "sample":
        out = model_output.clone()
        out[..., steps, :] = prefix
        return out
    signal, noise = _alphas(scheduler, t, sample)
    x0 = (sample - noise * model_output) / signal
    x0[..., steps, :] = prefix
    return (sample - signal * x0) / noise


def conditional_sample(
    model,
    batch_size: int,
    global_cond: Tensor,
    generator: torch.Generator | None = None,
    noise: Tensor | None = None,
    prefix: Tensor | None = None,
    first_step: int = 0,
) -> Tensor:
    """LeRobot's ``DiffusionModel.conditional_sample``, or, given a committed prefix, its loop with the prefix
    inpainted at every step (the same draws).

    Args:
        model: a LeRobot ``DiffusionModel`` (one member).
        batch_size: chunks to sample. global_cond: (batch_size, G).
        generator: optional RNG. noise: optional (batch_size, T, A) initial noise.
        prefix: optional (L, A) committed actions. first_step: the chunk index of the first.

    Returns:
        (batch_size, T, A) sampled chunks.
    """
    if prefix is None:
        return model.conditional_sample(batch_size, global_cond=global_cond, generator=generator, noise=noise)
    parameter = next(model.parameters())
    if noise is None:
        shape = (batch_size, model.config.horizon, model.config.action_feature.shape[0])
        noise = torch.randn(shape, dtype=parameter.dtype, device=parameter.device, generator=generator)
    sample = noise
    scheduler = model.noise_scheduler
    scheduler.set_timesteps(model.num_inference_steps)
    for t in scheduler.timesteps:
        steps = torch.full(sample.shape[:1], t, dtype=torch.long, device=sample.device)
        model_output = model.unet(sample, steps, global_cond=global_cond)
        model_output = inpaint_model_output(model_output, sample, int(t), scheduler, prefix, first_step)
        sample = scheduler.step(model_output, t, sample, generator=generator).prev_sample
    return sample
