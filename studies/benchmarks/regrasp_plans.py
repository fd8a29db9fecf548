"""How far each planned regrasp lies from the needle, and how often the scripted expert aimed at it extracts.

On the extraction task's nominal seeds (the episode starts at the end of the expert's own throw, the needle held
at its tail with the episode's grasp), for each source of the plan (``sim.regrasp_target``: ``marks``, the arc
planned through the registered marks; ``release``, the needle where the jaw lets go of it, placed by the grasp
model): the distance from the plan's jaw point to the jaw point that grasps the needle where the expert regrasps
it (mm), and the angle between the two jaw orientations (degrees), read from the simulator at reset; then the
scripted expert aimed at that plan (``ExpertConfig.regrasp_aim``) run to the task's limit on the same seeds: how
many extractions succeed. Prints one JSON object.

    .venv/bin/python studies/benchmarks/regrasp_plans.py [--episodes 50] [--seed 0] [--output F.json]
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
from _lockstep import emit, machine  # noqa: E402

import lerobot_suture  # noqa: E402,F401
from lerobot_suture.experiments.metrics import wilson_interval  # noqa: E402
from lerobot_suture.expert import ExpertConfig, ScriptedExpert, iter_expert_steps  # noqa: E402
from lerobot_suture.sim.extraction import REGRASP_ANGLE, planned_regrasp  # noqa: E402
from lerobot_suture.sim.geometry import grasp_transform, jaw_holding, rotation_angle_of  # noqa: E402
from lerobot_suture.sim.regrasp_target import REGRASP_SOURCES, released_regrasp  # noqa: E402
from lerobot_suture.sim.tasks import TASKS  # noqa: E402


def plan_of(source: str, u) -> tuple[np.ndarray, np.ndarray]:
    """The planned regrasp's jaw pose at reset (position m, rotation) from ``source``."""
    if source == "marks":
        return planned_regrasp(u.entry_point, u.exit_point, u.phantom_rotation[:, 2])
    return released_regrasp(*u.jaw_pose())  # at reset the jaw still holds the needle: the release pose


def summary(values: list[float]) -> dict:
    return {
        "median": round(float(np.median(values)), 3),
        "q90": round(float(np.percentile(values, 90)), 3),
        "max": round(float(np.max(values)), 3),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0, help="the first seed")
    parser.add_argument("--output", type=Path)
    args = parser.parse_args()
    env = gym.make(TASKS["extraction"].gym_id, obs_type="state", disable_env_checker=True)
    seeds = list(range(args.seed, args.seed + args.episodes))
    sources = {}
    for source in REGRASP_SOURCES:
        distances, angles, successes = [], [], 0
        for seed in seeds:
            obs, _ = env.reset(seed=seed)
            u = env.unwrapped
            own = jaw_holding(*u.needle_pose(), *grasp_transform(REGRASP_ANGLE, 0.0, 0.0))
            plan = plan_of(source, u)
            distances.append(float(np.linalg.norm(plan[0] - own[0])) * 1e3)
            angles.append(float(np.degrees(rotation_angle_of(plan[1].T @ own[1]))))
            expert = ScriptedExpert(ExpertConfig(regrasp_aim=source))
            expert.reset(env)
            steps = list(iter_expert_steps(env, expert, obs))
            successes += bool(steps[-1].info["is_success"])
        sources[source] = {
            "distance_to_the_needle_s_regrasp_mm": summary(distances),
            "angle_to_it_deg": summary(angles),
            "expert_aimed_at_it": {
                "successes": successes,
                "episodes": len(seeds),
                "wilson_95": [round(x, 3) for x in wilson_interval(successes, len(seeds))],
            },
        }
        print(source, sources[source], flush=True)
    emit(
        {
            "command": "python studies/benchmarks/regrasp_plans.py "
            + f"--episodes {args.episodes} --seed {args.seed}",
            "task": "extraction",
            "seeds": [seeds[0], seeds[-1]],
            "sources": sources,
            "machine": machine(),
        },
        args.output,
    )


if __name__ == "__main__":
    main()
