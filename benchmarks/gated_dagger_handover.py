"""Gated DAgger on the simulated arm vs the env path's enforced gate: do handovers fall at the same prediction?

For each of the paper's four perturbation scenarios and ``--episodes`` seeds:

- env path: ``rollout_episode`` with the gate enforced and the scripted surgeon taking over (what
  ``lerobot-suture experiments`` runs for its enforced-gate table); the handover step;
- robot path: LeRobot's ``lerobot-rollout --strategy.type=gated_dagger`` (the real command) on ``suture_sim``
  with the same scene seeds, the ``suture_scripted`` teleoperator; the handover is the first frame labelled
  ``intervention``.

Both without the CBF (``--strategy.cbf.enabled=false``; the env path has none), so the two differ only in the
path. Bar: handovers within 2 control steps of each other. Prints one JSON object.

    .venv/bin/python benchmarks/gated_dagger_handover.py --policy-path DIR [--episodes 10] [--output FILE]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
from _report import emit  # noqa: E402
from tqdm import tqdm  # noqa: E402

from lerobot_suture.experiments.metrics import wilson_interval  # noqa: E402
from lerobot_suture.experiments.paper import EXPERIMENTS  # noqa: E402
from lerobot_suture.sim.task import TASK  # noqa: E402

NEEDS = "a calibrated ensemble (--policy-path)"
TOLERANCE_STEPS = 2
FIRST_SEED = 4_100_000
BIN = Path(sys.executable).parent


def env_path_handovers(policy_path: Path, scenario: str, seeds: list[int]) -> list[int | None]:
    from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy
    from lerobot_suture.runtime.rollout import make_scenario_env, rollout_episode

    runner = PolicyRunner.from_pretrained(policy_path, GateMode.ENFORCE)
    env = make_scenario_env(env_kwargs_for_policy(runner.policy.config), scenario)
    try:
        return [rollout_episode(env, runner, seed, surgeon="expert").handover_step for seed in seeds]
    finally:
        env.close()


def robot_path_handovers(policy_path: Path, scenario: str, seeds: list[int], work: Path) -> list[int | None]:
    """The real ``lerobot-rollout`` command; episode ``n`` plays the scene of ``seeds[0] + n``."""
    from lerobot.datasets import LeRobotDataset

    root = work / f"rollout_{scenario}"
    command = [
        str(BIN / "lerobot-rollout"),
        "--strategy.type=gated_dagger",
        "--strategy.cbf.enabled=false",
        f"--policy.path={policy_path}",
        "--teleop.type=suture_scripted",
        "--device=cpu",
        "--fps=1000",
        "--return_to_initial_position=false",
        "--play_sounds=false",
        "--robot.type=suture_sim",
        f"--robot.seed={seeds[0]}",
        f"--robot.scenario={scenario}",
        "--robot.clock=fast",
        "--robot.episode_end=hold",
        f"--dataset.repo_id=local/rollout_{scenario}",
        f"--dataset.root={root}",
        "--dataset.fps=10",
        f"--dataset.num_episodes={len(seeds)}",
        "--dataset.episode_time_s=600",
        "--dataset.reset_time_s=0",
        f"--dataset.single_task={TASK}",
        "--dataset.push_to_hub=false",
    ]
    environ = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
    result = subprocess.run(command, env=environ, stdin=subprocess.DEVNULL, capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError((result.stdout + result.stderr)[-4000:])
    dataset = LeRobotDataset(f"local/rollout_{scenario}", root=root)
    episodes = np.asarray(dataset.hf_dataset["episode_index"])
    intervention = np.asarray(dataset.hf_dataset["intervention"]).reshape(-1).astype(bool)
    out: list[int | None] = []
    for episode in range(len(seeds)):
        labels = intervention[episodes == episode]
        out.append(int(np.argmax(labels)) if labels.any() else None)
    return out


def compare(env: list[int | None], robot: list[int | None]) -> dict:
    both = [(a, b) for a, b in zip(env, robot, strict=True) if a is not None and b is not None]
    agree = sum(abs(a - b) <= TOLERANCE_STEPS for a, b in both) + sum(
        a is None and b is None for a, b in zip(env, robot, strict=True)
    )
    n = len(env)
    low, high = wilson_interval(agree, n)
    return {
        "episodes": n,
        "env_handovers": sum(a is not None for a in env),
        "robot_handovers": sum(b is not None for b in robot),
        "agree_within_2_steps": agree,
        "agree_rate": round(agree / n, 4) if n else None,
        "agree_wilson95": [round(low, 4), round(high, 4)],
        "abs_difference_steps": sorted(abs(a - b) for a, b in both),
        "env_handover_steps": env,
        "robot_handover_steps": robot,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy-path", type=Path, required=True, help="a calibrated ensemble_diffusion")
    parser.add_argument("--episodes", type=int, default=10, help="per scenario")
    parser.add_argument("--output", type=Path, default=None)
    args = parser.parse_args()

    report: dict = {"benchmark": "gated_dagger_handover", "policy": str(args.policy_path), "scenarios": {}}
    start = time.perf_counter()
    scenarios = [scenario for _, scenario, _ in EXPERIMENTS]
    with tempfile.TemporaryDirectory() as tmp:
        for group, scenario in enumerate(tqdm(scenarios, desc="scenarios", file=sys.stderr)):
            seeds = [FIRST_SEED + 1000 * group + k for k in range(args.episodes)]
            try:
                env = env_path_handovers(args.policy_path, scenario, seeds)
                robot = robot_path_handovers(args.policy_path, scenario, seeds, Path(tmp))
            except KeyboardInterrupt:
                print(f"interrupted in {scenario}", file=sys.stderr)
                break
            report["scenarios"][scenario] = {"seeds": seeds, **compare(env, robot)}
    blocks = report["scenarios"].values()
    agree, n = sum(b["agree_within_2_steps"] for b in blocks), sum(b["episodes"] for b in blocks)
    low, high = wilson_interval(agree, n) if n else (float("nan"), float("nan"))
    report["total"] = {
        "episodes": n,
        "agree_within_2_steps": agree,
        "agree_rate": round(agree / n, 4) if n else None,
        "agree_wilson95": [round(low, 4), round(high, 4)],
    }
    report["tolerance_steps"] = TOLERANCE_STEPS
    report["wall_s"] = round(time.perf_counter() - start, 1)
    emit(report, args.output)


if __name__ == "__main__":
    main()
