"""The simulated arm on LeRobot's robot path against ``lerobot-eval``, and the real-time loop's period.

Two figures, each from LeRobot's own console scripts on the same trained policy:

1. **Rollout matches eval.** ``lerobot-eval --env.type=suture`` on ``--episodes`` seeds from ``--seed``,
   and ``lerobot-rollout --strategy.type=episodic --robot.type=suture_sim`` on the same seeds (dataset
   episode N plays the scene of ``seed + N``) with the as-fast-as-possible clock and
   ``--robot.episode_end=hold`` (the arm stops at its episode's end, as ``lerobot-eval`` stops an env).
   The rollout's outcome per seed is read from the robot's trace (the step where the throw ended, or the
   env's 10 s limit came). The episodic strategy, not ``base``, because it resets the policy between
   episodes, as ``lerobot-eval`` does; ``base`` runs one continuous scene.
2. **Real time holds.** ``lerobot-rollout --strategy.type=base`` with the real-time clock at 10 Hz for
   ``--realtime-s`` seconds: the period between executed control steps (p50, p99, max) and the share of
   periods over 110 ms.

Prints one JSON object (and writes it to ``--out`` when given)::

    .venv/bin/python benchmarks/robot_path.py --policy-path DIR [--episodes 50] [--seed 2000000]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

NEEDS = "a trained policy (--policy-path)"
BIN = Path(sys.executable).parent
CONTROL_PERIOD_S = 0.1
LATE_FACTOR = 1.1


def _environ() -> dict:
    return {
        **os.environ,
        "HF_HUB_OFFLINE": "1",
        "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
        "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "egl"),
    }


def _run(name: str, args: list[str], log: Path) -> float:
    """Run a LeRobot console script; returns its wall time (s). Its output goes to ``log``."""
    start = time.perf_counter()
    with log.open("w") as out:
        result = subprocess.run(
            [str(BIN / name), *args], env=_environ(), stdin=subprocess.DEVNULL, stdout=out, stderr=out
        )
    if result.returncode != 0:
        raise RuntimeError(f"{name} failed (exit {result.returncode}); its log: {log}")
    return time.perf_counter() - start


def _image_size(policy_path: Path) -> int:
    config = json.loads((policy_path / "config.json").read_text())
    shape = config["input_features"]["observation.images.endoscope"]["shape"]
    return int(shape[-1])


def eval_outcomes(policy_path: Path, episodes: int, seed: int, work: Path) -> tuple[dict[int, bool], float]:
    out = work / "eval"
    seconds = _run(
        "lerobot-eval",
        [
            f"--policy.path={policy_path}",
            "--env.type=suture",
            f"--eval.n_episodes={episodes}",
            "--eval.batch_size=1",
            f"--seed={seed}",
            "--policy.device=cpu",
            f"--output_dir={out}",
        ],
        work / "eval.log",
    )
    successes = json.loads((out / "eval_info.json").read_text())["per_task"][0]["metrics"]["successes"]
    # One env: lerobot-eval seeds episode i with seed + i.
    return {seed + i: bool(success) for i, success in enumerate(successes)}, seconds


def trace_outcomes(trace: list[dict]) -> dict[int, bool | None]:
    """Per scene seed: the outcome at the step its episode ended (None: it never ended)."""
    outcomes: dict[int, bool | None] = {}
    for line in trace:
        seed = int(line["seed"])
        if outcomes.get(seed) is not None:
            continue
        ended = line["throw_over"] or line.get("time_limit", False)
        outcomes[seed] = bool(line["is_success"]) if ended else None
    return outcomes


def rollout_outcomes(
    policy_path: Path, episodes: int, seed: int, episode_s: float, work: Path
) -> tuple[dict[int, bool | None], float]:
    trace = work / "rollout_trace.jsonl"
    seconds = _run(
        "lerobot-rollout",
        [
            "--strategy.type=episodic",
            f"--policy.path={policy_path}",
            "--device=cpu",
            "--fps=50",  # the loop's pace; the fast clock never waits, the held arm ends each scene
            "--return_to_initial_position=false",
            "--robot.type=suture_sim",
            f"--robot.seed={seed}",
            f"--robot.image_size={_image_size(policy_path)}",
            "--robot.clock=fast",
            "--robot.episode_end=hold",
            f"--robot.trace_path={trace}",
            "--dataset.repo_id=local/rollout_robot_path_benchmark",
            f"--dataset.root={work / 'rollout_dataset'}",
            "--dataset.fps=10",
            f"--dataset.num_episodes={episodes}",
            f"--dataset.episode_time_s={episode_s}",
            "--dataset.reset_time_s=0",
            "--dataset.single_task=Insert the curved suture needle at the entry point and drive it out "
            "through the exit point.",
            "--dataset.push_to_hub=false",
            "--play_sounds=false",
            "--display_data=false",
        ],
        work / "rollout.log",
    )
    lines = [json.loads(line) for line in trace.read_text().splitlines()]
    return trace_outcomes(lines), seconds


def realtime_periods(policy_path: Path, seconds: float, seed: int, work: Path) -> dict:
    trace = work / "realtime_trace.jsonl"
    _run(
        "lerobot-rollout",
        [
            "--strategy.type=base",
            f"--policy.path={policy_path}",
            "--device=cpu",
            "--fps=10",
            f"--duration={seconds}",
            "--return_to_initial_position=false",
            "--robot.type=suture_sim",
            f"--robot.seed={seed}",
            f"--robot.image_size={_image_size(policy_path)}",
            "--robot.clock=realtime",
            f"--robot.trace_path={trace}",
            "--play_sounds=false",
            "--display_data=false",
        ],
        work / "realtime.log",
    )
    times = np.array([json.loads(line)["wall_time"] for line in trace.read_text().splitlines()])
    periods = np.diff(times)
    return {
        "steps": int(times.size),
        "period_s": {
            "p50": round(float(np.percentile(periods, 50)), 4),
            "p99": round(float(np.percentile(periods, 99)), 4),
            "max": round(float(periods.max()), 4),
            "mean": round(float(periods.mean()), 4),
        },
        "late_share": round(float(np.mean(periods > LATE_FACTOR * CONTROL_PERIOD_S)), 4),
        "rate_hz": round(float(1.0 / periods.mean()), 3),
        "holds_10_hz": bool(np.percentile(periods, 99) <= LATE_FACTOR * CONTROL_PERIOD_S),
    }


def main() -> None:
    from lerobot_suture.experiments.metrics import wilson_interval

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy-path", type=Path, required=True)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=2_000_000, help="first test seed (the experiments')")
    parser.add_argument("--episode-s", type=float, default=20.0, help="wall time of a rollout episode")
    parser.add_argument("--realtime-s", type=float, default=60.0)
    parser.add_argument("--out", type=Path)
    parser.add_argument(
        "--work-dir", type=Path, help="the commands' outputs and logs (default: a new temp dir)"
    )
    args = parser.parse_args()
    work = args.work_dir or Path(tempfile.mkdtemp(prefix="robot_path_"))
    if work.exists() and any(work.iterdir()):
        raise SystemExit(f"--work-dir {work} is not empty: the commands' outputs would mix; pass a new one.")
    work.mkdir(parents=True, exist_ok=True)
    evaluated, eval_s = eval_outcomes(args.policy_path, args.episodes, args.seed, work)
    rolled, rollout_s = rollout_outcomes(args.policy_path, args.episodes, args.seed, args.episode_s, work)
    realtime = realtime_periods(args.policy_path, args.realtime_s, args.seed, work)
    seeds = [args.seed + k for k in range(args.episodes)]
    eval_successes = sum(evaluated[s] for s in seeds)
    finished = [s for s in seeds if rolled.get(s) is not None]
    rollout_successes = sum(bool(rolled[s]) for s in finished)
    low, high = (round(b, 6) for b in wilson_interval(eval_successes, len(seeds)))
    rollout_rate = rollout_successes / len(seeds)
    result = {
        "policy_path": str(args.policy_path),
        "episodes": args.episodes,
        "first_seed": args.seed,
        "eval": {
            "successes": eval_successes,
            "success_rate": eval_successes / len(seeds),
            "wilson95": [low, high],
            "seconds": round(eval_s, 1),
        },
        "rollout": {
            "successes": rollout_successes,
            "success_rate": rollout_rate,
            "wilson95": [round(b, 6) for b in wilson_interval(rollout_successes, len(seeds))],
            "unfinished_episodes": len(seeds) - len(finished),
            "seconds": round(rollout_s, 1),
        },
        "same_outcome_share": sum(evaluated[s] == rolled.get(s) for s in seeds) / len(seeds),
        "rollout_within_eval_interval": bool(low <= rollout_rate <= high),
        "realtime": realtime,
        "work_dir": str(work),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "load_at_end": os.getloadavg()},
    }
    text = json.dumps(result, indent=2)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
