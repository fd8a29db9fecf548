"""Where a trained policy's pickups end: reached, closed on the needle, grasped in range, lifted clear.

Rolls the policy out on the leaderboard's nominal ``pickup`` test seeds (``--seed`` is the leaderboard's
base, so the episodes are its ``nominal`` cell's: same seeds, the CBF on, each episode's noise from its
seed, the gate reporting) and reads the simulator's privileged state at every control step. A pickup
succeeds when the jaw holds the needle inside the grasp ranges an insertion is tested in (arc angle within
4 degrees of 165, within 0.5 mm along the jaw, roll within 0.05 rad, the right way round) and has lifted
all of it 5 mm clear of the tissue (``lerobot_suture.sim.pickup``). Prints one JSON object: how many
episodes closed the jaw on the needle, how many held a grasp in range, how many lifted it clear, and, for
each grasp the jaw closed on, its errors against those ranges (medians and the share inside each), and,
for the episodes whose jaw never caught the needle, the closest its jaw came to the pose that holds the
needle in the nominal grasp (mm and degrees).

    .venv/bin/python studies/benchmarks/pickup_failures.py --policy-path DIR [--episodes 50] [--output F.json]
"""

from __future__ import annotations

import math
import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402
from _lockstep import jaw_pose_error, roll_out_lockstep, run_nominal_seeds  # noqa: E402

import lerobot_suture  # noqa: E402,F401
from lerobot_suture.experiments.metrics import wilson_interval  # noqa: E402
from lerobot_suture.sim.pickup import LIFT_HEIGHT  # noqa: E402
from lerobot_suture.sim.task import GRASP_ANGLE, GRASP_RANGES  # noqa: E402

NEEDS = "a trained pickup policy (--policy-path)"
TASK = "pickup"


def grasp_errors(parameters: tuple[float, float, float], reversed_grasp: bool) -> dict:
    """A grasp's distance from the nominal one: arc angle (deg), depth along the jaw (mm), roll (rad)."""
    angle, depth, roll = parameters
    return {
        "angle_error_deg": math.degrees(abs(angle - GRASP_ANGLE)),
        "depth_mm": 1e3 * abs(depth),
        "roll_rad": abs(roll),
        "reversed": bool(reversed_grasp),
    }


def approach_error(u) -> tuple[float, float]:
    """How far the jaw is from the pose that would hold the needle in the nominal grasp (mm, deg)."""
    return jaw_pose_error(u, u.nominal_grasp_in_jaw)


def roll_out(runner, env_kwargs: dict, seeds: list[int]) -> list[dict]:
    """``seeds`` in lockstep (one batch), the CBF on; per episode what the jaw did with the needle."""
    out = [
        {
            "seed": s,
            "closed_on_needle": False,
            "grasp_in_range": False,
            "clearance_mm": None,
            "grasps": [],
            "closest_mm": math.inf,
            "closest_rotation_deg": None,
            "was_held": False,
        }
        for s in seeds
    ]

    def on_step(i: int, u, info: dict) -> None:
        ep = out[i]
        if not ep["closed_on_needle"]:  # the reach before the first grasp
            distance, rotation = approach_error(u)
            if distance < ep["closest_mm"]:
                ep["closest_mm"], ep["closest_rotation_deg"] = distance, rotation
        if u.needle_grasped:
            if not ep["was_held"]:  # a new grasp: record how it sits
                ep["grasps"].append(grasp_errors(u.grasp_parameters, u.grasp_reversed))
            ep["closed_on_needle"] = True
            if u.needle_in_throw_grasp:
                ep["grasp_in_range"] = True
                clearance = 1e3 * u.needle_clearance
                ep["clearance_mm"] = max(ep["clearance_mm"] or -math.inf, clearance)
        ep["was_held"] = bool(u.needle_grasped)
        ep["success"] = bool(info["is_success"])
        ep["steps"] = int(u.step_index)

    roll_out_lockstep(runner, env_kwargs, TASK, seeds, on_step)
    for ep in out:
        del ep["was_held"]
    return out


def summarize(episodes: list[dict]) -> dict:
    """Counts with 95% Wilson intervals, and the first grasp's errors against the ranges."""
    n = len(episodes)

    def count(key: str) -> dict:
        k = sum(bool(ep[key]) for ep in episodes)
        return {"episodes": k, "rate": k / n, "interval": list(wilson_interval(k, n))}

    angle_range, depth_range, roll_range = GRASP_RANGES["narrow"]
    first = [ep["grasps"][0] for ep in episodes if ep["grasps"]]
    grasps = {}
    if first:
        grasps = {
            "first_grasps": len(first),
            "median_angle_error_deg": float(np.median([g["angle_error_deg"] for g in first])),
            "median_depth_mm": float(np.median([g["depth_mm"] for g in first])),
            "median_roll_rad": float(np.median([g["roll_rad"] for g in first])),
            "angle_inside": float(
                np.mean([g["angle_error_deg"] <= math.degrees(angle_range) for g in first])
            ),
            "depth_inside": float(np.mean([g["depth_mm"] <= 1e3 * depth_range for g in first])),
            "roll_inside": float(np.mean([g["roll_rad"] <= roll_range for g in first])),
            "reversed": float(np.mean([g["reversed"] for g in first])),
            "grasps_per_episode_that_closed": float(
                np.mean([len(ep["grasps"]) for ep in episodes if ep["grasps"]])
            ),
        }
    missed = [ep for ep in episodes if not ep["closed_on_needle"]]
    if missed:  # the episodes whose jaw never caught the needle: how near its reach came
        closest = np.array([ep["closest_mm"] for ep in missed])
        grasps["missed"] = {
            "episodes": len(missed),
            "median_closest_mm": float(np.median(closest)),
            "within_1mm": float(np.mean(closest <= 1.0)),
            "within_3mm": float(np.mean(closest <= 3.0)),
            "median_rotation_at_closest_deg": float(np.median([ep["closest_rotation_deg"] for ep in missed])),
        }
    lifted = sum(
        ep["clearance_mm"] is not None and ep["clearance_mm"] >= 1e3 * LIFT_HEIGHT for ep in episodes
    )
    return {
        "closed_on_needle": count("closed_on_needle"),
        "grasp_in_range": count("grasp_in_range"),
        "lifted_clear_in_range": lifted,
        "success": count("success"),
        "ranges": {
            "angle_deg": math.degrees(angle_range),
            "depth_mm": 1e3 * depth_range,
            "roll_rad": roll_range,
            "lift_mm": 1e3 * LIFT_HEIGHT,
        },
        **grasps,
    }


def main() -> None:
    run_nominal_seeds(TASK, "pickup_failures", __doc__.splitlines()[0], roll_out, summarize)


if __name__ == "__main__":
    main()
