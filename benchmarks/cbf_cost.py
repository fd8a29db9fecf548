"""What the CBF costs a throw: success with the filter and without it, in every condition the guarantee covers.

A filter that froze the arm would pass every violation bar, so its cost is part of its result. For each condition
(``attack_episodes.CONDITIONS`` within the bounds: tissue still, servoed, moved after insertion, breathing at the
declared bound; on the robot path also an arm lagging 10, 20 or 30%), ``--episodes`` nominal throws (seeds from
``--first-seed``) with ``CBFConfig(enabled=True)`` and the same seeds with the filter only watching
(``enabled=False``). The actor is the scripted expert, or a trained policy (``--policy-path``): on the robot
path it acts from the arm's observation, through the condition's faults, and its action goes through the
robot's ``suture_cbf`` step, as ``lerobot-rollout`` runs it.
Harm is counted as in ``benchmarks/cbf_adversary.py``, at every physics step.

Prints one JSON object: per condition, with and without the filter, success (and its Wilson 95% interval),
control steps the filter changed per episode, episodes with harm, mean tissue strain (mm); and the cost, the
success without the filter less the success with it, in points.

    .venv/bin/python benchmarks/cbf_cost.py --path env [--episodes 100] [--policy-path DIR] [--output FILE]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import asdict
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
from _attack_paths import make_path  # noqa: E402
from _report import emit, machine, write  # noqa: E402
from tqdm import tqdm  # noqa: E402

from lerobot_suture.experiments.attack_episodes import CONDITIONS, AttackEpisode  # noqa: E402
from lerobot_suture.experiments.metrics import wilson_interval  # noqa: E402
from lerobot_suture.expert import ScriptedExpert  # noqa: E402
from lerobot_suture.safety.cbf_config import CBFConfig  # noqa: E402
from lerobot_suture.sim.tasks import task_spec  # noqa: E402

ENV_CONDITIONS = ("still", "phantom_servo", "phantom_moved_after_insertion", "breathing_at_bound")
ROBOT_CONDITIONS = (*ENV_CONDITIONS, "arm_lag_0.1", "arm_lag_0.2", "arm_lag_0.3")


class ExpertActor:
    """The scripted expert, acting on the path's scene."""

    def reset(self, path) -> None:
        self.expert = ScriptedExpert()
        self.expert.reset(path.scene)

    def act(self, path) -> np.ndarray:
        return self.expert.act(path.scene)


class PolicyActor:
    """A trained policy, acting from the path's observations."""

    def __init__(self, runner):
        self.runner = runner

    def reset(self, path) -> None:
        self.runner.reset()

    def act(self, path) -> np.ndarray:
        return self.runner.act(path.observation)


def throw(path, actor, seed: int) -> dict:
    """One nominal throw of ``actor`` on ``path`` from ``seed``: its outcome, the filter's interventions, harm."""
    path.reset(seed)
    actor.reset(path)
    episode = AttackEpisode(family="nominal", seed=seed)
    for _ in range(task_spec(path.task).max_episode_steps):
        step = path.send(actor.act(path))
        episode.record(path, step)
        if step.over:
            break
    return {
        "success": bool(step.info["is_success"]),
        "interventions": episode.interventions,
        "harmed": episode.violation_steps > 0,
        "strain_mm": float(step.info["tissue_strain"]) * 1e3,
    }


def summarize(outcomes: list[dict]) -> dict:
    n = len(outcomes)
    successes = sum(o["success"] for o in outcomes)
    low, high = wilson_interval(successes, n)
    return {
        "episodes": n,
        "success": round(successes / n, 4),
        "success_interval_95": [round(low, 4), round(high, 4)],
        "interventions_per_episode": round(float(np.mean([o["interventions"] for o in outcomes])), 3),
        "episodes_harmed": sum(o["harmed"] for o in outcomes),
        "tissue_strain_mm_mean": round(float(np.mean([o["strain_mm"] for o in outcomes])), 4),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--path", choices=("env", "robot"), default="env")
    parser.add_argument(
        "--conditions", default=None, help="comma-separated names (default: all for the path)"
    )
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--first-seed", type=int, default=1000)
    parser.add_argument("--policy-path", type=Path, default=None, help="a trained policy")
    parser.add_argument("--output", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args()

    allowed = ENV_CONDITIONS if args.path == "env" else ROBOT_CONDITIONS
    names = args.conditions.split(",") if args.conditions else list(allowed)
    if unknown := [n for n in names if n not in allowed]:
        parser.error(f"conditions {unknown} are not measured on the {args.path} path; it has {list(allowed)}")
    env_kwargs: dict = {}
    actor = ExpertActor()
    if args.policy_path is not None:
        from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy

        runner = PolicyRunner.from_pretrained(args.policy_path, GateMode.REPORT)
        env_kwargs = env_kwargs_for_policy(runner.policy.config)
        actor = PolicyActor(runner)
    seeds = range(args.first_seed, args.first_seed + args.episodes)
    report: dict = {
        "benchmark": "cbf_cost",
        "command": " ".join(["python", *sys.argv]),
        "path": args.path,
        "actor": str(args.policy_path) if args.policy_path else "scripted expert",
        "seeds": [seeds.start, seeds.stop],
        "conditions": {},
    }
    start = time.perf_counter()
    progress = tqdm(
        total=2 * len(names) * len(seeds), desc=f"{args.path}-path cost", unit="episode", file=sys.stderr
    )
    for name in names:
        block: dict = {"condition": asdict(CONDITIONS[name])}
        for label, enabled in (("cbf_on", True), ("cbf_off", False)):
            path = make_path(args.path, name, CBFConfig(enabled=enabled), env_kwargs)
            outcomes = []
            try:
                for seed in seeds:
                    outcomes.append(throw(path, actor, seed))
                    progress.update()
            finally:
                path.close()
            block[label] = summarize(outcomes)
        block["cost_points"] = round(100 * (block["cbf_off"]["success"] - block["cbf_on"]["success"]), 2)
        report["conditions"][name] = block
        report["wall_s"] = round(time.perf_counter() - start, 1)
        report["machine"] = machine()
        if args.output is not None:
            write(report, args.output)
    progress.close()
    emit(report, args.output)


if __name__ == "__main__":
    main()
