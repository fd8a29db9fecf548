"""The pick-up scripted (``sim.pickup_servo``) on the running suture's board seeds, measured apart from any learned
policy: the scripted expert makes the first throw and lays the needle down (or loses it, where the scenario drops
it), then the servo picks it up, planned from where the jaw last held it and the marks alone. What the chain's
``--scripted_pick_up=true`` brings to a throw. Each scenario of the running suture, the CBF on; the grasp is judged
with the simulator's own (the ranges an insertion is tested in), which the servo never reads::

    .venv/bin/python benchmarks/scripted_pick_up.py --output docs/results/benchmarks/scripted_pick_up.json
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
from _report import emit, machine

EPISODE_FIELDS = ("seed", "held", "ready", "closings", "steps", "arc_error_deg", "depth_mm", "roll_rad")
"""An episode's row in the report's ``per_episode``, in this order."""
PICK_UP_STEPS = 300
"""Control steps the servo is given (its reach, up to five closings and the searches between them)."""


def episode(env, seed: int) -> dict:
    """The expert until its first pick-up, then the servo; how the servo's pick-up ended."""
    from lerobot_suture.expert import ScriptedExpert
    from lerobot_suture.sim.pickup import grasp_ready_for_throw
    from lerobot_suture.sim.pickup_servo import NeedleRelease, PickupServo, resting_needle
    from lerobot_suture.sim.task import GRASP_ANGLE
    from lerobot_suture.sim.wound_marks import MARKS_DIM

    observation, _ = env.reset(seed=seed)
    expert, release = ScriptedExpert(task="running_suture"), NeedleRelease()
    expert.reset(env)
    for _ in range(env.spec.max_episode_steps):
        action = expert.act(env)
        if expert.stage == "pick_up" and release.pose is not None:
            break
        release.update(observation["agent_pos"], expert.stage)
        observation, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            return dict(zip(EPISODE_FIELDS, (seed, False, False, 0, 0, None, None, None), strict=True))
    marks = observation["environment_state"][:MARKS_DIM]
    needle = resting_needle(*release.pose, release.held_angle, float(np.mean(marks[[2, 5]])))
    servo, steps = PickupServo(needle, marks), 0
    while not servo.done and steps < PICK_UP_STEPS:
        steps += 1
        action = servo.act(observation["agent_pos"], observation["environment_state"][:MARKS_DIM])
        observation, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            break
    base = env.unwrapped
    grasped = bool(base.needle_grasped)
    angle, depth, roll = base.grasp_parameters if grasped else (math.nan,) * 3
    ready = grasped and grasp_ready_for_throw(base.grasp_parameters, base.grasp_reversed)
    measured = (
        (round(math.degrees(angle - GRASP_ANGLE), 3), round(1e3 * depth, 3), round(roll, 4))
        if grasped
        else (None, None, None)
    )
    row = (seed, servo.held and grasped, bool(ready), servo.closings, steps, *measured)
    return dict(zip(EPISODE_FIELDS, row, strict=True))


def main() -> None:
    from lerobot_suture.experiments.metrics import wilson_interval
    from lerobot_suture.leaderboard import cells
    from lerobot_suture.runtime.rollout import make_scenario_env
    from lerobot_suture.safety.cbf_config import CBFConfig
    from lerobot_suture.sim.tasks import task_spec

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=50, help="test episodes a scenario")
    parser.add_argument("--seed", type=int, default=7_000_000, help="the leaderboard's base of test seeds")
    parser.add_argument(
        "--image-size", type=int, default=96, help="the endoscope's size (px); nothing reads it"
    )
    parser.add_argument("--output", type=Path)
    args = parser.parse_args()

    env_kwargs = {
        "task": "running_suture",
        "obs_type": "pixels_agent_pos",
        "marks": True,
        "image_size": args.image_size,
    }
    by_scenario = {}
    for scenario in task_spec("running_suture").scenarios:
        env = make_scenario_env(env_kwargs, scenario, CBFConfig(enabled=True))
        start = time.perf_counter()
        seeds = cells.condition_seeds(args.seed, "running_suture", scenario, args.episodes)
        try:
            episodes = [episode(env, seed) for seed in seeds]
        finally:
            env.close()
        held = sum(e["held"] for e in episodes)
        ready = sum(e["ready"] for e in episodes)
        by_scenario[scenario] = {
            "episodes": len(episodes),
            "held": held,
            "held_interval": [round(v, 4) for v in wilson_interval(held, len(episodes))],
            "ready_for_throw": ready,
            "ready_interval": [round(v, 4) for v in wilson_interval(ready, len(episodes))],
            "first_closing_held": sum(e["held"] and e["closings"] == 1 for e in episodes),
            "seconds": round(time.perf_counter() - start, 1),
            "per_episode": [[e[k] for k in EPISODE_FIELDS] for e in episodes],
        }
        print(f"{scenario}: held {held}/{len(episodes)}, ready {ready}", flush=True)
    emit(
        {
            "task": "running_suture",
            "cbf": True,
            "per_episode_fields": EPISODE_FIELDS,
            "scenarios": by_scenario,
            "machine": machine(),
        },
        args.output,
    )


if __name__ == "__main__":
    main()
