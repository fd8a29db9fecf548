"""Roll a policy out on a batch of a task's nominal seeds in lockstep, as the leaderboard's cells do.

Shared by the benchmarks that read the simulator's privileged state while a trained policy acts (where a
task's episodes end): the same envs (the CBF on), seeding and batching as a leaderboard cell, with a
callback after every env step, and the command line that runs them on the leaderboard's nominal seeds. Unlike
a cell, the envs do not record the needle tip's physics-rate trace, so ``agent_pos`` is a physics step behind
the simulator's kinematics, as in a recording; a policy that leans on that step ends differently in a cell.
"""

from __future__ import annotations

import argparse
import math
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))  # the product's _report
from _report import emit, machine  # noqa: E402

from lerobot_suture.leaderboard.cells import condition_seeds  # noqa: E402
from lerobot_suture.runtime.policy import env_kwargs_for_policy, parse_overrides, reporting_runner  # noqa: E402
from lerobot_suture.runtime.rollout import make_scenario_env  # noqa: E402
from lerobot_suture.safety.cbf_config import CBFConfig  # noqa: E402
from lerobot_suture.sim.geometry import jaw_holding, rotation_angle_of  # noqa: E402


def jaw_pose_error(u, grasp_in_jaw: tuple[np.ndarray, np.ndarray]) -> tuple[float, float]:
    """How far the jaw of env ``u`` is from the pose that would hold the needle in ``grasp_in_jaw`` (the
    needle's pose in the jaw frame): position (mm) and rotation (deg)."""
    target_pos, target_rot = jaw_holding(*u.needle_pose(), *grasp_in_jaw)
    jaw_pos, jaw_rot = u.jaw_pose()
    angle = rotation_angle_of(target_rot.T @ jaw_rot)
    return 1e3 * float(np.linalg.norm(jaw_pos - target_pos)), math.degrees(angle)


def roll_out_lockstep(
    runner, env_kwargs: dict, task: str, seeds: list[int], on_step: Callable[[int, object, dict], None]
) -> None:
    """``seeds`` of ``task``'s nominal condition in one batch; ``on_step(i, env.unwrapped, info)`` after each
    step of episode ``i`` until it terminates or truncates."""
    envs = [
        make_scenario_env({**env_kwargs, "task": task}, "nominal", CBFConfig(enabled=True)) for _ in seeds
    ]
    torch.manual_seed(seeds[0])
    observations = [env.reset(seed=seed)[0] for env, seed in zip(envs, seeds, strict=True)]
    runner.reset(seeds=seeds)
    tasks = [env.unwrapped.task_description for env in envs]
    done = [False] * len(envs)
    for _ in range(envs[0].spec.max_episode_steps):
        if all(done):
            break
        actions = runner.act_batch(observations, tasks)
        for i, env in enumerate(envs):
            if done[i]:
                continue
            observations[i], _, terminated, truncated, info = env.step(actions[i])
            on_step(i, env.unwrapped, info)
            done[i] = bool(terminated or truncated)
    for env in envs:
        env.close()


def run_nominal_seeds(
    task: str,
    benchmark: str,
    description: str,
    roll_out: Callable[[object, dict, list[int]], list[dict]],
    summarize: Callable[[list[dict]], dict],
) -> None:
    """A failure benchmark's command line: ``roll_out`` a trained ``task`` policy on the leaderboard's nominal
    seeds in batches, ``summarize`` the episodes, print (and with ``--output`` write) the JSON report."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--policy-path", type=Path, required=True, help=f"a trained {task} pretrained_model")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=7_000_000, help="the leaderboard's base test seed")
    parser.add_argument("--batch-envs", type=int, default=10)
    parser.add_argument("--output", type=Path, help="write the JSON here too")
    parser.add_argument(
        "--override",
        nargs="*",
        default=[],
        metavar="FIELD=VALUE",
        help="policy config fields at load, e.g. n_action_steps=8 uncertainty_samples_per_member=32",
    )
    args = parser.parse_args()
    if args.episodes < 1 or args.batch_envs < 1:
        parser.error(f"--episodes and --batch-envs must be >= 1. Got {args.episodes}, {args.batch_envs}.")
    if not (args.policy_path / "config.json").is_file():
        sys.exit(
            f"No trained policy at {args.policy_path} (no config.json): pass a pretrained_model directory."
        )
    try:
        overrides = parse_overrides(args.override)
    except ValueError as error:
        parser.error(str(error))
    runner = reporting_runner(args.policy_path, overrides=overrides)
    env_kwargs = env_kwargs_for_policy(runner.policy.config)  # a relative policy composes its own actions
    seeds = condition_seeds(args.seed, task, "nominal", args.episodes)
    start = time.perf_counter()
    episodes = []
    for k in range(0, len(seeds), args.batch_envs):
        episodes += roll_out(runner, env_kwargs, seeds[k : k + args.batch_envs])
        print(f"{len(episodes)}/{len(seeds)} episodes", file=sys.stderr, flush=True)
    report = {
        "benchmark": benchmark,
        "command": " ".join(["python", *sys.argv]),
        "machine": {**machine(), "python": platform.python_version(), "torch": torch.__version__},
        "policy_path": str(args.policy_path),
        "seed": args.seed,
        "seconds": round(time.perf_counter() - start, 1),
        "summary": summarize(episodes),
        "episodes": episodes,
    }
    emit(report, args.output)
