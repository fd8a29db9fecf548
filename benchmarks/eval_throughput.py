"""Closed-loop evaluation throughput of a trained policy: episodes per minute of `rollout_seeds` at several
`batch_envs`, and whether every configuration gives the same episodes.

Each configuration runs the same nominal test seeds (the CBF on, the gate reporting, as the experiments
run). A seed's diffusion noise comes from the seed itself (`PolicyRunner`), so batching is an exact
speed-up: the check compares every episode with the first configuration's (success, length, the step of
the gate's first alarm, and the largest relative difference of its uncertainty scores, which float rounding
in a batched GEMM may move by ~1e-6). Time it with nothing else running; prints JSON.

    python benchmarks/eval_throughput.py --policy-path outputs/.../pretrained_model [--episodes 16]
        [--batch-envs 1 8 16] [--threads N] [--output FILE]
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from _report import emit, machine  # noqa: E402

from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy  # noqa: E402
from lerobot_suture.runtime.rollout import make_scenario_env, rollout_seeds  # noqa: E402
from lerobot_suture.runtime.seeds import episode_seeds  # noqa: E402
from lerobot_suture.safety.cbf_config import CBFConfig  # noqa: E402

TEST_SEED = 8_000_000  # apart from recording, calibration and the commands' test seeds


def episode_record(log) -> dict:
    return {
        "seed": log.seed,
        "success": bool(log.success),
        "steps": len(log.steps),
        "first_alarm_step": log.first_alarm_step,
        "scores": log.scores,
    }


def compare(reference: list[dict], other: list[dict]) -> dict:
    """Whether ``other``'s episodes are ``reference``'s: outcomes equal, scores within float rounding."""
    same = all(
        (a["seed"], a["success"], a["steps"], a["first_alarm_step"])
        == (b["seed"], b["success"], b["steps"], b["first_alarm_step"])
        for a, b in zip(reference, other, strict=True)
    )
    rel = 0.0
    for a, b in zip(reference, other, strict=True):
        if len(a["scores"]) == len(b["scores"]) and len(a["scores"]):
            finite = np.isfinite(a["scores"])
            if finite.any():
                diff = np.abs(a["scores"][finite] - b["scores"][finite]) / np.maximum(
                    np.abs(a["scores"][finite]), 1e-12
                )
                rel = max(rel, float(diff.max()))
    return {"identical_outcomes": same, "max_relative_score_difference": rel}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--policy-path", type=Path, required=True)
    parser.add_argument("--episodes", type=int, default=16)
    parser.add_argument("--batch-envs", type=int, nargs="+", default=[1, 8, 16])
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--output", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    runner = PolicyRunner.from_pretrained(args.policy_path, GateMode.REPORT)
    env_kwargs = env_kwargs_for_policy(runner.policy.config)
    seeds = episode_seeds(TEST_SEED, 0, args.episodes)

    def make_env():
        return make_scenario_env(env_kwargs, "nominal", CBFConfig(enabled=True))

    rollout_seeds(make_env, runner, seeds[:1], 1, desc="warm-up")
    rows, reference = [], None
    for batch_envs in args.batch_envs:
        start = time.perf_counter()
        logs = rollout_seeds(make_env, runner, seeds, batch_envs, desc=f"batch_envs={batch_envs}")
        seconds = time.perf_counter() - start
        episodes = [episode_record(log) for log in logs]
        row = {
            "batch_envs": batch_envs,
            "episodes": len(logs),
            "seconds": round(seconds, 1),
            "episodes_per_min": round(60.0 * len(logs) / seconds, 1),
            "success_rate": float(np.mean([e["success"] for e in episodes])),
            "mean_steps": float(np.mean([e["steps"] for e in episodes])),
        }
        if reference is None:
            reference = episodes
        else:
            row.update(compare(reference, episodes))
        rows.append(row)
    base = rows[0]["episodes_per_min"]
    for row in rows:
        row["speed_up"] = round(row["episodes_per_min"] / base, 2) if base else math.nan
    emit(
        {
            "benchmark": "eval_throughput",
            "policy_path": str(args.policy_path),
            "policy_type": runner.policy.config.type,
            "torch_threads": args.threads,
            "machine": machine(),
            "configurations": rows,
        },
        args.output,
    )


if __name__ == "__main__":
    main()
