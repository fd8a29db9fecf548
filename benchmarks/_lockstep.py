"""Roll a policy out on a batch of a task's nominal seeds in lockstep, as the leaderboard's cells do.

Shared by the benchmarks that read the simulator's privileged state while a trained policy acts (where a
task's episodes end): the same envs (the CBF on), seeding and batching as a leaderboard cell, with a
callback after every env step.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from lerobot_suture.runtime.rollout import make_scenario_env
from lerobot_suture.safety.cbf_config import CBFConfig


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
