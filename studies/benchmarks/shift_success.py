#!/usr/bin/env python
"""How often policies succeed in the nominal scene and under shifts (``lerobot_suture.sim.shifts``).

Each policy is rolled out with its gate reporting only (no calibration needed) on the same seeds: nominal
episodes, then each shift. Prints one JSON line per policy with the success rate per condition and its
95% Wilson interval. Used for ablations such as LeRobot's image transforms on top of appearance
randomization (two checkpoints at the same training step, trained with and without them):

    python studies/benchmarks/shift_success.py --policy A/pretrained_model --policy B/pretrained_model \\
        --shifts dim_light@0.2 smoke_haze@0.2 camera_roll@0.08 --episodes 20
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys

NEEDS = "trained policies (--policy, once per policy)"
DEFAULT_SHIFTS = (
    "dim_light@0.2",
    "smoke_haze@0.2",
    "instrument_colour@0.15",
    "tissue_colour@0.03",
    "camera_roll@0.08",
    "image_noise@0.02",
)
SEED = 7_000_000  # apart from recording, calibration, test and collection seeds


def main() -> None:
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", action="append", required=True, help="a pretrained_model directory")
    parser.add_argument("--shifts", nargs="*", default=list(DEFAULT_SHIFTS), help="NAME@MAGNITUDE each")
    parser.add_argument("--episodes", type=int, default=20, help="episodes per condition")
    parser.add_argument("--batch_envs", type=int, default=10)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()

    from lerobot_suture.experiments.metrics import wilson_interval
    from lerobot_suture.runtime.policy import env_kwargs_for_policy, reporting_runner
    from lerobot_suture.runtime.rollout import make_scenario_env, rollout_seeds
    from lerobot_suture.sim.shifts import Shift

    shifts = [Shift.parse(s) for s in args.shifts]
    seeds = [SEED + k for k in range(args.episodes)]
    for path in args.policy:
        with contextlib.redirect_stdout(sys.stderr):  # LeRobot prints while loading; stdout stays JSON lines
            runner = reporting_runner(path, args.device)
        env_kwargs = env_kwargs_for_policy(runner.policy.config)
        result = {"policy": path, "episodes": args.episodes, "success": {}}
        for shift in [None, *shifts]:
            label = "nominal" if shift is None else shift.label
            logs = rollout_seeds(
                lambda shift=shift, kw=env_kwargs: make_scenario_env(kw, "nominal", shift=shift),
                runner,
                seeds,
                args.batch_envs,
                desc=f"{label}",
            )
            successes = sum(log.success for log in logs)
            low, high = wilson_interval(successes, len(logs))
            result["success"][label] = {"rate": successes / len(logs), "wilson95": [low, high]}
        print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
