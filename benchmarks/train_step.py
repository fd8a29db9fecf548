#!/usr/bin/env python
"""Cost of one training step of the ensemble: forward, backward and AdamW on a batch of the preset's size.

Prints one JSON object: the median wall-clock and CPU seconds per step and the samples per second, in
full precision and under bfloat16 autocast (what `lerobot-train --policy.use_amp=true` turns on), with
and without the endoscope image (the state-only variant shows what the N vision encoders cost). The
optimizer is the ensemble's preset (PyTorch's fused AdamW); one more bf16 run with LeRobot's plain
`AdamWConfig` (PyTorch's per-tensor loop on the CPU) gives `fused_optimizer_speedup_bf16`. The data
is random and already normalized, so dataset decoding (a worker process in `lerobot-train`, about 8 ms
per sample) is not counted. On 2 cores `lerobot-train` took about 1.5 s per step in fp32 with LeRobot's
AdamW and 1.0 s under bf16 with the fused AdamW.

    python benchmarks/train_step.py                               # CPU preset, 4 members, 2 threads
    python benchmarks/train_step.py --n-members 5 --batch-size 8
"""

from __future__ import annotations

import argparse
import json
import platform

import torch
from _policy_builders import random_observation
from ensemble_latency import load_preset_config, preset_file, timed
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.optim import AdamWConfig
from lerobot.utils.constants import ACTION, OBS_ENV_STATE
from lerobot_policy_ensemble_diffusion.modeling_ensemble_diffusion import EnsembleDiffusionPolicy


def training_batch(config, batch_size: int, seed: int) -> dict[str, torch.Tensor]:
    """A normalized training batch: observations (B, n_obs_steps, ...) and an action chunk (B, horizon, A)."""
    batch = random_observation(config, batch_size=batch_size, seed=seed)
    g = torch.Generator().manual_seed(seed + 1)
    if config.env_state_feature is not None:
        batch[OBS_ENV_STATE] = torch.randn(batch_size, config.n_obs_steps, 10, generator=g)
    batch[ACTION] = torch.randn(batch_size, config.horizon, config.action_feature.shape[0], generator=g)
    batch["action_is_pad"] = torch.zeros(batch_size, config.horizon, dtype=torch.bool)
    return batch


def step_cost(
    config, batch_size: int, bf16: bool, warmup: int, repeats: int, seed: int, fused: bool = True
) -> dict:
    torch.manual_seed(seed)
    policy = EnsembleDiffusionPolicy(config).train()
    preset = config.get_optimizer_preset()  # fused: what lerobot-train builds for the ensemble
    if not fused:  # LeRobot's own AdamWConfig: PyTorch's per-tensor loop on the CPU
        preset = AdamWConfig(
            lr=preset.lr, betas=preset.betas, eps=preset.eps, weight_decay=preset.weight_decay
        )
    optimizer = preset.build(policy.parameters())
    batch = training_batch(config, batch_size, seed)

    def step():
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            loss, _ = policy.forward(batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    wall, cpu = timed(step, torch.device("cpu"), warmup, repeats)
    return {"s_per_step": wall, "cpu_s_per_step": cpu, "samples_per_s": batch_size / wall}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--preset", default="cpu", help="preset name in policies/presets or a JSON path")
    parser.add_argument("--n-members", type=int, default=4, help="the reference run trains 4")
    parser.add_argument("--batch-size", type=int, default=0, help="0: the preset's batch_size")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads (0: leave torch's default)")
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.threads > 0:
        torch.set_num_threads(args.threads)

    batch_size = args.batch_size or preset_file(args.preset)["batch_size"]
    with_image = load_preset_config(args.preset, n_members=args.n_members, device="cpu")
    state_only = load_preset_config(args.preset, n_members=args.n_members, device="cpu")
    # Without the image LeRobot's diffusion needs an environment state: a (10,) stand-in costs nothing.
    state_only.input_features = {
        **{k: v for k, v in state_only.input_features.items() if k not in state_only.image_features},
        OBS_ENV_STATE: PolicyFeature(type=FeatureType.ENV, shape=(10,)),
    }
    results = {}
    for name, config in (("image_and_state", with_image), ("state_only", state_only)):
        for precision, bf16 in (("fp32", False), ("bf16_autocast", True)):
            results[f"{name}_{precision}"] = step_cost(
                config, batch_size, bf16, args.warmup, args.repeats, args.seed
            )
    results["image_and_state_bf16_autocast_unfused_optimizer"] = step_cost(
        with_image, batch_size, True, args.warmup, args.repeats, args.seed, fused=False
    )
    report = {
        "benchmark": "train_step",
        "preset": args.preset,
        "n_members": args.n_members,
        "batch_size": batch_size,
        "threads": torch.get_num_threads(),
        "cpu": platform.processor() or platform.machine(),
        "torch": torch.__version__,
        **results,
        "bf16_speedup": results["image_and_state_fp32"]["s_per_step"]
        / results["image_and_state_bf16_autocast"]["s_per_step"],
        "fused_optimizer_speedup_bf16": results["image_and_state_bf16_autocast_unfused_optimizer"][
            "s_per_step"
        ]
        / results["image_and_state_bf16_autocast"]["s_per_step"],
        "vision_share_fp32": 1.0
        - results["state_only_fp32"]["s_per_step"] / results["image_and_state_fp32"]["s_per_step"],
    }
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
