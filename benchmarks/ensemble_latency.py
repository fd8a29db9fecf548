#!/usr/bin/env python
"""Latency of one ensemble prediction: one member, the naive loop over members, the batched ensemble.

Prints one JSON object (``--output`` writes it to a file too): the command, the machine and, under
``result``, the timings. For N members at batch 1 it times, on the same observation:
  one_member_s   one LeRobot `DiffusionModel.generate_actions` call (one member's chunk);
  naive_loop_s   that call for every member in a Python loop (what an ensemble costs without batching);
  batched_s      `EnsembleDiffusionPolicy.predict_action_distribution` with the fused members (every member's
                 chunk plus mean, covariance and score);
  batched_sampling_s  the fused members' sampling alone (no statistics), for a like-for-like comparison.
Each figure is the median wall-clock time of --repeats timed runs after --warmup runs; `cpu_time` gives the
medians of this process's CPU time, which are robust to other load on a shared machine (1 thread).

    python benchmarks/ensemble_latency.py                      # CPU preset, N=5, batch 1, 1 thread
    python benchmarks/ensemble_latency.py --preset paper --device cuda
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import torch
from _policy_builders import (
    NEEDLE_KEYPOINTS_DIM,
    SUTURE_INPUT_FEATURES,
    SUTURE_OUTPUT_FEATURES,
    fake_dataset_stats,
    random_observation,
)
from _report import emit, machine
from lerobot.utils.constants import OBS_IMAGES
from lerobot_policy_ensemble_diffusion.modeling_ensemble_diffusion import EnsembleDiffusionPolicy

from lerobot_suture.runtime.policy import parse_overrides

PRESETS_DIR = Path(__file__).resolve().parents[1] / "policies" / "presets"


def preset_file(preset: str) -> dict:
    """A preset's JSON (the whole `lerobot-train` config): a name in policies/presets or a JSON path."""
    path = Path(preset) if preset.endswith(".json") else PRESETS_DIR / f"{preset}.json"
    return json.loads(path.read_text())


def load_preset_config(preset: str, **overrides):
    """The ensemble config of a preset file (policy section), with the suture features filled in."""
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot_policy_ensemble_diffusion import EnsembleDiffusionConfig
    from lerobot_policy_ensemble_diffusion.configuration_ensemble_diffusion import NEEDLE_KEYPOINTS_KEY

    policy = dict(preset_file(preset)["policy"])
    policy.pop("type")
    for key in ("resize_shape", "down_dims"):
        if isinstance(policy.get(key), list):
            policy[key] = tuple(policy[key])
    policy.update(
        input_features=dict(SUTURE_INPUT_FEATURES), output_features=dict(SUTURE_OUTPUT_FEATURES), **overrides
    )
    if policy.get("needle_keypoints_weight", 0) > 0:
        # A training target only (never an input, so no cost at inference), but the config checks it is there.
        policy["input_features"][NEEDLE_KEYPOINTS_KEY] = PolicyFeature(
            type=FeatureType.STATE, shape=(NEEDLE_KEYPOINTS_DIM,)
        )
    return EnsembleDiffusionConfig(**policy)


def timed(fn, device: torch.device, warmup: int, repeats: int) -> tuple[float, float]:
    """Median wall-clock seconds and median CPU seconds of this process (robust on a shared machine)."""
    for _ in range(warmup):
        fn()
    wall, cpu = [], []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize()
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return statistics.median(wall), statistics.median(cpu)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--preset", default="cpu", help="preset name in policies/presets or a JSON path")
    parser.add_argument("--n-members", type=int, default=5)
    parser.add_argument("--batch-size", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (0: leave torch's default)")
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="FIELD=JSON",
        help="override policy fields, e.g. down_dims=[32,64]",
    )
    parser.add_argument("--output", type=Path, help="write the JSON here too")
    args = parser.parse_args()
    load = machine()  # read before the timing load

    if args.threads > 0:
        torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    device = torch.device(args.device)
    overrides = {k: tuple(v) if isinstance(v, list) else v for k, v in parse_overrides(args.set).items()}
    config = load_preset_config(args.preset, n_members=args.n_members, device=args.device, **overrides)
    policy = EnsembleDiffusionPolicy(config, dataset_stats=fake_dataset_stats()).to(device).eval()

    batch = {k: v.to(device) for k, v in random_observation(config, batch_size=args.batch_size).items()}
    model_batch = dict(batch)
    model_batch[OBS_IMAGES] = torch.stack([batch[k] for k in config.image_features], dim=-4)
    members = [m.diffusion for m in policy.members]

    def one_member():
        members[0].generate_actions(model_batch)

    def naive_loop():
        for member in members:
            member.generate_actions(model_batch)

    def batched():
        # One chunk per member, like for like with `one_member` (the preset may sample K > 1 per member).
        policy.predict_action_distribution(batch, samples_per_member=1)

    fused = policy._fused_members()

    def batched_sampling():
        fused.sample(fused.encode(model_batch))

    with torch.inference_mode():
        results = {
            name: timed(fn, device, args.warmup, args.repeats)
            for name, fn in (
                ("one_member_s", one_member),
                ("naive_loop_s", naive_loop),
                ("batched_s", batched),
                ("batched_sampling_s", batched_sampling),
            )
        }
    result = {
        "benchmark": "ensemble_latency",
        "preset": args.preset,
        "n_members": config.n_members,
        "batch_size": args.batch_size,
        "device": str(device) if device.type != "cuda" else torch.cuda.get_device_name(device),
        "cpu": platform.processor() or platform.machine(),
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "image_input": list(next(iter(config.image_features.values())).shape),
        "resize_shape": list(config.resize_shape) if config.resize_shape else None,
        "crop_shape": list(config.crop_shape) if config.crop_shape else None,
        "down_dims": list(config.down_dims),
        "n_obs_steps": config.n_obs_steps,
        "horizon": config.horizon,
        "noise_scheduler": config.noise_scheduler_type,
        "inference_steps": policy.members[0].diffusion.num_inference_steps,
        "overrides": args.set,
        "repeats": args.repeats,
        **{k: round(wall, 5) for k, (wall, _) in results.items()},
        "cpu_time": {k: round(cpu, 5) for k, (_, cpu) in results.items()},
        "speedup_batched_vs_naive_loop": round(results["naive_loop_s"][0] / results["batched_s"][0], 3),
        "batched_over_one_member": round(results["batched_s"][0] / results["one_member_s"][0], 3),
    }
    command = " ".join(["python", "benchmarks/ensemble_latency.py", *sys.argv[1:]])
    emit({"command": command, "machine": load, "result": result}, args.output)


if __name__ == "__main__":
    main()
