"""A trained policy on the running suture, throw by throw, with the O.O.D. gate reporting and the CBF filtering.

Rolls the policy out on ``--episodes`` test seeds of ``running_suture`` (nominal scene; the seeds of the
paper's experiments, disjoint from recording and calibration), the gate in reporting mode (the policy keeps
control; its alarms are logged) and the CBF on every step, re-armed for each throw. Prints one JSON object:
per throw, how many episodes reached it, how many put it on the marks (of all, and of those reaching it,
with 95% Wilson intervals), its entry and exit errors, how often the gate alarmed on failed and on good
throws, and what the CBF did (active steps, interventions, the smallest barrier value at the physics rate);
and the whole suture. ``--figure`` draws it, ``--markdown`` writes it as a table.

    .venv/bin/python benchmarks/running_suture_reference.py --policy-path DIR [--episodes 50] [--out F.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

import lerobot_suture  # noqa: E402,F401
from lerobot_suture.experiments.per_throw import (  # noqa: E402
    per_throw_markdown,
    per_throw_table,
    plot_per_throw,
)
from lerobot_suture.runtime.policy import env_kwargs_for_policy, reporting_runner  # noqa: E402
from lerobot_suture.runtime.rollout import make_scenario_env, rollout_seeds  # noqa: E402
from lerobot_suture.runtime.seeds import episode_seeds  # noqa: E402
from lerobot_suture.safety.cbf_config import CBFConfig  # noqa: E402
from lerobot_suture.sim.running_suture import N_THROWS  # noqa: E402

NEEDS = "a trained, calibrated running-suture ensemble (--policy-path)"
TASK = "running_suture"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--policy-path", type=Path, required=True, help="a trained, calibrated pretrained_model"
    )
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument(
        "--seed", type=int, default=2_000_000, help="base of the test seeds (the experiments')"
    )
    parser.add_argument("--batch-envs", type=int, default=8)
    parser.add_argument("--out", type=Path, help="write the JSON here too")
    parser.add_argument("--figure", type=Path, help="draw the table into this PNG")
    parser.add_argument("--markdown", type=Path, help="write the table as markdown here")
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1. Got {args.episodes}.")
    runner = reporting_runner(args.policy_path)
    calibration = runner.policy.ood_calibration
    if calibration is None:
        parser.error(
            f"The policy at {args.policy_path} has no O.O.D. calibration; run `lerobot-suture calibrate "
            f"--policy.path={args.policy_path} --dataset_root=DIR` on its running-suture dataset first."
        )
    env_kwargs = {**env_kwargs_for_policy(runner.policy.config), "task": TASK}
    seeds = episode_seeds(args.seed, 0, args.episodes)
    start = time.perf_counter()
    logs = rollout_seeds(
        lambda: make_scenario_env(env_kwargs, "nominal", CBFConfig(enabled=True), trace=True),
        runner,
        seeds,
        args.batch_envs,
        desc="running suture",
    )
    table = per_throw_table(logs, N_THROWS)
    result = {
        "benchmark": "running_suture_reference",
        "policy_path": str(args.policy_path),
        "task": TASK,
        "scenario": "nominal",
        "seeds": [seeds[0], seeds[-1]],
        "gate": {"mode": "report", "calibration_mode": calibration.mode, "alpha": calibration.alpha},
        "cbf": "enabled",
        "episode_steps_median": float(np.median([len(log.steps) for log in logs])),
        "wall_s": round(time.perf_counter() - start, 1),
        **table,
    }
    output = {
        "command": "python benchmarks/running_suture_reference.py "
        + " ".join(f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items() if v is not None),
        "machine": f"{os.cpu_count()}-core {platform.machine()} CPU, Python {platform.python_version()}, "
        f"torch {torch.__version__.split('+')[0]}, {torch.get_num_threads()} threads",
        "result": result,
    }
    print(json.dumps(output, indent=2, default=float))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(output, separators=(",", ":"), default=float) + "\n")
    if args.markdown:
        args.markdown.write_text(per_throw_markdown(table))
    if args.figure:
        plot_per_throw(table, args.figure, f"running suture, {args.episodes} test seeds: throw by throw")


if __name__ == "__main__":
    main()
