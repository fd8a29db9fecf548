"""The extract scripted from end to end on the leaderboard's extraction cells: the regrasp servo
(``sim.regrasp_servo``) takes the needle's tip, the pull (``sim.pull_servo``) turns it out, and no learned policy
acts. What the chain's ``--scripted_regrasp=true --scripted_pull=true`` brings to a throw, measured apart from the
policies around it: the board's test seeds of every extraction scenario, the CBF on, a jaw that reads empty after
holding the tip regrasped as the chain does::

    .venv/bin/python benchmarks/scripted_extract.py --output docs/results/benchmarks/scripted_extract.json
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from _report import emit, machine

EPISODE_FIELDS = ("seed", "success", "steps", "tissue_strain_mm", "regrasps", "closings", "pulled_rad")
"""An episode's row in the report's ``per_episode``, in this order."""


def episode(env, seed: int) -> dict:
    """One extraction episode under the scripted regrasp and pull; its outcome and what the servos did."""
    from lerobot_suture.sim.regrasp_target import REGRASP_TARGET_DIM
    from lerobot_suture.sim.scripted_extract import ScriptedExtract
    from lerobot_suture.sim.wound_marks import MARKS_DIM

    observation, _ = env.reset(seed=seed)
    extract, info, steps = ScriptedExtract(pull=True), {}, 0
    while steps < env.spec.max_episode_steps:
        steps += 1
        pose = observation["agent_pos"]
        regrasp = observation["environment_state"][MARKS_DIM : MARKS_DIM + REGRASP_TARGET_DIM]
        action = extract.act(pose, regrasp)
        if action is None:  # every closing missed, or the turn is over: hold still, the jaw closed
            action = np.asarray(pose, dtype=np.float32).copy()
            action[-1] = 1.0
        observation, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break
    strain_mm = round(1e3 * float(info.get("tissue_strain", np.nan)), 3)
    pulled = round(extract.pull.angle, 3) if extract.pull is not None else 0.0
    outcome = (
        bool(info.get("is_success")),
        steps,
        strain_mm,
        extract.regrasps,
        extract.closings,
    )
    return dict(zip(EPISODE_FIELDS, (seed, *outcome, pulled), strict=True))


def main() -> None:
    from lerobot_suture.experiments.metrics import wilson_interval
    from lerobot_suture.leaderboard import cells
    from lerobot_suture.runtime.rollout import make_scenario_env
    from lerobot_suture.safety.cbf_config import CBFConfig
    from lerobot_suture.sim.tasks import task_spec

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=50, help="test episodes a scenario")
    parser.add_argument("--seed", type=int, default=7_000_000, help="the leaderboard's base of test seeds")
    parser.add_argument("--regrasp-from", choices=("marks", "release"), default="marks")
    parser.add_argument(
        "--image-size", type=int, default=96, help="the endoscope's size (px); nothing reads it"
    )
    parser.add_argument("--output", type=Path)
    args = parser.parse_args()

    env_kwargs = {
        "task": "extraction",
        "obs_type": "pixels_agent_pos",
        "marks": True,
        "regrasp_target": True,
        "regrasp_from": args.regrasp_from,
        "image_size": args.image_size,
    }
    by_scenario = {}
    for scenario in task_spec("extraction").scenarios:
        env = make_scenario_env(env_kwargs, scenario, CBFConfig(enabled=True))
        start = time.perf_counter()
        seeds = cells.condition_seeds(args.seed, "extraction", scenario, args.episodes)
        try:
            episodes = [episode(env, seed) for seed in seeds]
        finally:
            env.close()
        successes = sum(e["success"] for e in episodes)
        strain = [e["tissue_strain_mm"] for e in episodes]
        by_scenario[scenario] = {
            "episodes": len(episodes),
            "successes": successes,
            "success_interval": [round(v, 4) for v in wilson_interval(successes, len(episodes))],
            "tissue_strain_mm_median": float(np.median(strain)),
            "tissue_strain_mm_max": float(np.max(strain)),
            "first_closing_held": sum(e["closings"] == 1 and e["regrasps"] == 1 for e in episodes),
            "seconds": round(time.perf_counter() - start, 1),
            "per_episode": [[e[k] for k in EPISODE_FIELDS] for e in episodes],
        }
        print(f"{scenario}: {successes}/{len(episodes)}", flush=True)
    emit(
        {
            "task": "extraction",
            "regrasp_from": args.regrasp_from,
            "cbf": True,
            "per_episode_fields": EPISODE_FIELDS,
            "scenarios": by_scenario,
            "machine": machine(),
        },
        args.output,
    )


if __name__ == "__main__":
    main()
