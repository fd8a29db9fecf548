"""Scripted-expert quality: success rate over seeded nominal episodes, entry/exit error distribution.

Prints JSON. Target: >= 98% success over 200 seeded nominal episodes.

``--assume-nominal-grasp`` runs the expert as if the needle sat in the jaw at its nominal grasp (it does
not: the grasp is randomized per episode). That is all a policy which cannot see the needle in the jaw
can know. So its success is an upper bound on such a policy's, and its entry error a lower bound.
"""

from __future__ import annotations

import argparse
import json
import os

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

import lerobot_suture  # noqa: E402,F401
from lerobot_suture.expert import ExpertConfig  # noqa: E402
from lerobot_suture.runtime.expert_rollout import run_expert_episode  # noqa: E402
from lerobot_suture.sim.scenarios import SCENARIOS  # noqa: E402


def distribution(values: list[float]) -> dict:
    v = np.asarray([x for x in values if np.isfinite(x)]) * 1000.0
    if v.size == 0:
        return {"n": 0}
    return {
        "n": int(v.size),
        "median_mm": round(float(np.median(v)), 4),
        "p95_mm": round(float(np.percentile(v, 95)), 4),
        "max_mm": round(float(v.max()), 4),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--scenario_episodes", type=int, default=20)
    parser.add_argument("--assume-nominal-grasp", action="store_true")
    args = parser.parse_args()
    expert = ExpertConfig(assume_nominal_grasp=args.assume_nominal_grasp)

    nominal = [
        run_expert_episode(seed, expert_config=expert) for seed in tqdm(range(args.episodes), desc="nominal")
    ]
    result = {
        "benchmark": "expert_quality",
        "assume_nominal_grasp": args.assume_nominal_grasp,
        "episodes": args.episodes,
        "success_rate": float(np.mean([e.success for e in nominal])),
        "failed_seeds": [e.seed for e in nominal if not e.success],
        "steps_median": float(np.median([e.steps for e in nominal])),
        "entry_error": distribution([e.entry_error_m for e in nominal]),
        "exit_error": distribution([e.exit_error_m for e in nominal]),
        "tissue_strain": distribution([e.tissue_strain_m for e in nominal]),
        "bar_98_percent": float(np.mean([e.success for e in nominal])) >= 0.98,
        "scenarios": {},
    }
    for scenario in SCENARIOS[1:]:
        eps = [
            run_expert_episode(10_000 + seed, scenario, expert_config=expert)
            for seed in tqdm(range(args.scenario_episodes), desc=scenario)
        ]
        result["scenarios"][scenario] = {
            "episodes": len(eps),
            "success_rate": float(np.mean([e.success for e in eps])),
            "exit_error": distribution([e.exit_error_m for e in eps]),
        }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
