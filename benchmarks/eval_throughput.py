"""Closed-loop evaluation throughput of a trained policy: episodes per minute of `rollout_seeds` at several
`batch_envs` and `workers`, and whether every configuration gives the same episodes.

Each configuration runs the same nominal test seeds (the CBF on, the gate reporting, as the experiments
run). A seed's diffusion noise comes from the seed itself (`PolicyRunner`), so batching and worker
processes are exact speed-ups: the check compares every episode with the first configuration's: success, length and the step of
the gate's first alarm must be equal; the largest relative difference of its uncertainty scores is reported
(a batched GEMM rounds differently, and the closed loop carries a difference of ~1e-7 into the next
observations, so scores late in an episode may differ by percents while the outcomes stay the same). Time it with nothing else running; prints JSON.

    python benchmarks/eval_throughput.py --policy-path outputs/.../pretrained_model [--episodes 16]
        [--configs 1 8 8x2 16x2] [--output FILE]

A configuration is BATCH_ENVS or BATCH_ENVSxWORKERS. In one process torch takes its default threads (all
cores); each of W workers takes cores // W. Worker start-up (imports, loading the policy) is kept out of
`seconds`, the rollouts' wall time once the workers are up: `warmup_seconds` is the first call (start-up plus
one batch per worker).

`--baseline FILE` names this script's output from another version of the code (e.g. run from a worktree
of an earlier commit with `PYTHONPATH` on its packages, `--configs 1`): its first configuration is the
baseline every `speed_up_vs_baseline` divides by.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from _report import emit, machine  # noqa: E402

from lerobot_suture.pipelines.stages import code_commit  # noqa: E402
from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy  # noqa: E402
from lerobot_suture.runtime.rollout import make_scenario_env, rollout_seeds  # noqa: E402
from lerobot_suture.runtime.seeds import episode_seeds  # noqa: E402
from lerobot_suture.safety.cbf_config import CBFConfig  # noqa: E402

NEEDS = "a trained ensemble (--policy-path)"
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
    parser.add_argument("--configs", nargs="+", default=["1", "8", "8x2", "16x2"])
    parser.add_argument("--output", type=Path, default=None)
    parser.add_argument("--baseline", type=Path, default=None)
    args = parser.parse_args()

    runner = PolicyRunner.from_pretrained(args.policy_path, GateMode.REPORT)
    env_kwargs = env_kwargs_for_policy(runner.policy.config)
    seeds = episode_seeds(TEST_SEED, 0, args.episodes)

    make_env = functools.partial(make_scenario_env, env_kwargs, "nominal", CBFConfig(enabled=True))
    rollout_seeds(make_env, runner, seeds[:1], 1, desc="warm-up")
    rows, reference = [], None
    for config in args.configs:
        batch_envs, _, workers = config.partition("x")
        batch_envs, workers = int(batch_envs), int(workers or 1)
        warmup = 0.0
        if workers > 1:  # start the pool (and its envs) on one batch per worker, timed apart
            start = time.perf_counter()
            rollout_seeds(make_env, runner, seeds[: batch_envs * workers], batch_envs, workers=workers)
            warmup = time.perf_counter() - start
        start = time.perf_counter()
        spread = {"workers": workers} if workers > 1 else {}  # (an older rollout_seeds has no workers)
        logs = rollout_seeds(make_env, runner, seeds, batch_envs, desc=config, **spread)
        seconds = time.perf_counter() - start
        episodes = [episode_record(log) for log in logs]
        row = {
            "batch_envs": batch_envs,
            "workers": workers,
            "episodes": len(logs),
            "seconds": round(seconds, 1),
            "warmup_seconds": round(warmup, 1),
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
    baseline = None
    if args.baseline is not None:
        baseline = json.loads(args.baseline.read_text())
        baseline = {"file": str(args.baseline), **baseline["configurations"][0]}
    for row in rows:
        row["speed_up"] = round(row["episodes_per_min"] / base, 2) if base else math.nan
        if baseline is not None:
            row["speed_up_vs_baseline"] = round(row["episodes_per_min"] / baseline["episodes_per_min"], 2)
    emit(
        {
            "code_commit": code_commit(),
            "baseline": baseline,
            "benchmark": "eval_throughput",
            "policy_path": str(args.policy_path),
            "policy_type": runner.policy.config.type,
            "torch_threads_one_process": torch.get_num_threads(),
            "machine": machine(),
            "configurations": rows,
        },
        args.output,
    )


if __name__ == "__main__":
    main()
