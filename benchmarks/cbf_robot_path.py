"""The CBF on the robot path under attack: the ``suture_cbf`` step in the robot action pipeline, h at the physics rate.

Every scripted attack family of ``benchmarks/cbf_adversary.py`` (``--episodes-per-family`` each) is sent the way
``lerobot-rollout`` sends a policy's actions: ``SutureSim.get_observation`` -> the robot action pipeline holding
``suture_cbf`` (measured pose, grasp model, registered wound; no simulator state) -> ``send_action``; the arm
runs its tip-tracking controller (``lerobot_robot_suture.attacks``). Each fault setting is one block:

- ``none``; ``observation_latency`` 3 control steps (pose and image 0.3 s old); ``command_latency`` 3 (the arm
  executes the command sent 0.3 s earlier): the bar, 0 violations in >= 1,000 episodes each;
- ``arm_lag`` 0.2 (``--lag-episodes-per-family``): an arm that falls short of its target in pose space,
  rotation included, which leaves the straight tip segment the guarantee assumes: measured, not a bar.

Prints one JSON object (per block: episodes, active steps, violations, min h, intervention rate; per family).

    .venv/bin/python benchmarks/cbf_robot_path.py [--episodes-per-family 125] [--output FILE]

Ctrl-C stops early and still prints what was finished.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

from _report import emit, machine  # noqa: E402
from lerobot_robot_suture.attacks import RobotAttackEpisode, make_robot_path, run_robot_attack_episode  # noqa: E402
from lerobot_robot_suture.faults import FaultConfig  # noqa: E402
from tqdm import tqdm  # noqa: E402

from lerobot_suture.experiments.cbf_attacks import FAMILIES, summarize_attacks  # noqa: E402

BAR_EPISODES = 1000
BAR_BLOCKS = {
    "none": {},
    "observation_latency_3": {"observation_latency": 3},
    "command_latency_3": {"command_latency": 3},
}
LAG_BLOCKS = {"arm_lag_0.2": {"arm_lag": 0.2}}


def run_block(faults: dict, seeds: range, attack_steps: int, episodes: list, progress: tqdm) -> None:
    """Every family on ``seeds`` with the robot's ``faults``, appended to ``episodes`` as they finish."""
    robot_path = make_robot_path(faults=FaultConfig(**faults))
    try:
        for seed in seeds:
            for family in FAMILIES:
                episodes.append(run_robot_attack_episode(robot_path, family, seed, attack_steps))
                progress.update()
    finally:
        robot_path[0].disconnect()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes-per-family", type=int, default=125)
    parser.add_argument("--lag-episodes-per-family", type=int, default=25)
    parser.add_argument("--attack-steps", type=int, default=30)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args()

    blocks = [(name, faults, args.episodes_per_family) for name, faults in BAR_BLOCKS.items()]
    blocks += [(name, faults, args.lag_episodes_per_family) for name, faults in LAG_BLOCKS.items()]
    total = sum(n for *_, n in blocks) * len(FAMILIES)
    report: dict = {"benchmark": "cbf_robot_path", "families": list(FAMILIES), "blocks": {}}
    start = time.perf_counter()
    progress = tqdm(total=total, desc="robot-path attacks", unit="episode", file=sys.stderr)
    for name, faults, per_family in blocks:
        episodes: list[RobotAttackEpisode] = []
        seeds = range(args.first_seed, args.first_seed + per_family)
        try:
            run_block(faults, seeds, args.attack_steps, episodes, progress)
        except KeyboardInterrupt:
            print(f"interrupted in block {name}", file=sys.stderr)
            report["blocks"][name] = {"faults": faults, **summarize_attacks(episodes), "interrupted": True}
            break
        block = {"faults": faults, **summarize_attacks(episodes)}
        block["families"] = {f: summarize_attacks([e for e in episodes if e.family == f]) for f in FAMILIES}
        if name in BAR_BLOCKS:
            block["bar"] = {
                "episodes_min": BAR_EPISODES,
                "pass": block["episodes"] >= BAR_EPISODES and block["violations"]["physics_steps"] == 0,
            }
        report["blocks"][name] = block
    progress.close()
    bar_blocks = [b for n, b in report["blocks"].items() if n in BAR_BLOCKS]
    report["bar_pass"] = len(bar_blocks) == len(BAR_BLOCKS) and all(b["bar"]["pass"] for b in bar_blocks)
    report["wall_s"] = round(time.perf_counter() - start, 1)
    report["machine"] = machine()
    emit(report, args.output)


if __name__ == "__main__":
    main()
