"""The task family's scripted experts: success over seeded episodes of every task in each of its scenarios.

Prints JSON: per task and scenario, the success rate with its 95% Wilson interval, the failed seeds (the first
ten), the median episode length and the largest tissue strain. Bar: the expert succeeds in >= 95% of 100 seeds for each task (nominal scene).

    python benchmarks/task_family.py [--episodes 100] [--task pickup]
"""

from __future__ import annotations

import argparse
import json
import os

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

import lerobot_suture  # noqa: E402,F401
from lerobot_suture.experiments.metrics import wilson_interval  # noqa: E402
from lerobot_suture.runtime.expert_rollout import run_expert_episode  # noqa: E402
from lerobot_suture.sim.tasks import TASK_NAMES, TASKS  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=100, help="seeds per task and scenario")
    parser.add_argument("--task", choices=TASK_NAMES, action="append", help="repeatable; default: every task")
    args = parser.parse_args()
    result = {
        "benchmark": "task_family",
        "episodes": args.episodes,
        "seeds": [0, args.episodes - 1],
        "tasks": {},
    }
    for name in args.task or TASK_NAMES:
        spec = TASKS[name]
        rows = {}
        for scenario in spec.scenarios:
            episodes = [
                run_expert_episode(seed, scenario, task=name)
                for seed in tqdm(range(args.episodes), desc=f"{name} / {scenario}")
            ]
            successes = sum(e.success for e in episodes)
            low, high = wilson_interval(successes, len(episodes))
            rows[scenario] = {
                "success_rate": successes / len(episodes),
                "wilson_95": [round(low, 4), round(high, 4)],
                "failed": len(episodes) - successes,
                "failed_seeds_first_10": [e.seed for e in episodes if not e.success][:10],
                "steps_median": float(np.median([e.steps for e in episodes])),
                "tissue_strain_max_mm": round(1e3 * max(e.tissue_strain_m for e in episodes), 4),
            }
        result["tasks"][name] = {
            "gym_id": spec.gym_id,
            "max_episode_steps": spec.max_episode_steps,
            "scenarios": rows,
            "bar_95_percent_nominal": rows["nominal"]["success_rate"] >= 0.95,
        }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
