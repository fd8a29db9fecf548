"""Per-episode outcomes of the paper's experiments and of leaderboard cells on a small sample: what a refactor
must leave unchanged.

Runs ``lerobot-suture experiments`` on a trained, calibrated ensemble with a few episodes per condition (nominal,
the four scenarios, the CBF and the enforced gate) and keeps, per episode, its seed, success, first alarm, the
largest score and the gate's score trace rounded to 6 significant digits; per CBF and enforced-gate condition,
its metrics. Then the same policy's leaderboard cells on insertion (the CBF on and traced, a scenario and a
shift), two episodes each: success, first alarm, the smallest barrier at the physics rate, the tissue strain.
With ``--check FILE`` it compares them with a committed run and exits 1, naming each difference.

    .venv/bin/python benchmarks/episode_outcomes.py --policy-path DIR [--output FILE] [--check FILE]

The committed sample is ``docs/results/benchmarks/episode_outcomes.json`` (the reference policy of
``lerobot-suture reproduce``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _report import emit, machine

NEEDS = "a trained, calibrated ensemble (--policy-path), e.g. lerobot-suture reproduce's"
COUNTS = {
    "nominal_episodes": 4,
    "expert_episodes": 2,
    "needle_drop_runs": 2,
    "camera_moved_runs": 2,
    "phantom_servo_runs": 2,
    "phantom_moved_after_insertion_runs": 2,
    "cbf_runs": 2,
    "enforced_runs": 2,
}


def rounded(value, digits: int = 6):
    """``value`` with every float to ``digits`` significant digits (what a rerun on the same machine keeps),
    and without the paths of the run's files (``*_path``)."""
    if isinstance(value, float):
        return float(f"{value:.{digits}g}")
    if isinstance(value, list):
        return [rounded(v, digits) for v in value]
    if isinstance(value, dict):
        return {k: rounded(v, digits) for k, v in value.items() if not k.endswith("_path")}
    return value


LEADERBOARD_CONDITIONS = ("nominal", "needle_drop", "shift:dim_light@0.2")
LEADERBOARD_EPISODES = 2


def leaderboard_outcomes(policy_path: Path) -> dict:
    """The policy's leaderboard cells on insertion, per episode (the leaderboard's seeds, runner and env)."""
    from lerobot_suture.leaderboard import cells
    from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy

    runner = PolicyRunner.from_pretrained(policy_path, GateMode.REPORT)
    env_kwargs = env_kwargs_for_policy(runner.policy.config)
    found = {}
    for condition in LEADERBOARD_CONDITIONS:
        seeds = cells.condition_seeds(0, "insertion", condition, LEADERBOARD_EPISODES)
        logs, _ = cells.cell_episodes(runner, env_kwargs, "insertion", condition, seeds, LEADERBOARD_EPISODES)
        found[condition] = [
            {
                "seed": log.seed,
                "success": log.success,
                "first_alarm": log.first_alarm_step,
                "max_score": max((s.score for s in log.steps if s.new_prediction), default=None),
                "h_min_physics": log.h_min_physics,
                "tissue_strain": log.tissue_strain,
                "steps": len(log.steps),
            }
            for log in logs
        ]
    return rounded(found)


def outcomes(output_dir: Path) -> dict:
    """The per-episode outcomes of one experiments run in ``output_dir``."""
    traces = json.loads((output_dir / "traces.json").read_text())
    metrics = json.loads((output_dir / "metrics.json").read_text())
    episodes = {}
    for condition, runs in traces.items():
        if condition == "threshold":
            continue
        episodes[condition] = [
            {
                "seed": run["seed"],
                "success": run["success"],
                "first_alarm": next((k for k, a in enumerate(run["alarms"]) if a), None),
                "max_score": max(run["scores"], default=None),
                "scores": run["scores"],
            }
            for run in runs
        ]
    return rounded(
        {
            "threshold": traces["threshold"],
            "episodes": episodes,
            "cbf": metrics["cbf"],
            "gate_enforced": metrics["gate_enforced"],
        }
    )


def differences(ours, theirs, path: str = "") -> list[str]:
    """Where two outcome trees differ, as ``path: ours != theirs``."""
    if isinstance(ours, dict) and isinstance(theirs, dict):
        found = [f"{path}/{k}: missing" for k in sorted(set(theirs) - set(ours))]
        found += [f"{path}/{k}: not in the committed run" for k in sorted(set(ours) - set(theirs))]
        for key in sorted(set(ours) & set(theirs)):
            found += differences(ours[key], theirs[key], f"{path}/{key}")
        return found
    if isinstance(ours, list) and isinstance(theirs, list) and len(ours) == len(theirs):
        return [
            d
            for k, (a, b) in enumerate(zip(ours, theirs, strict=True))
            for d in differences(a, b, f"{path}[{k}]")
        ]
    return [] if ours == theirs else [f"{path}: {ours!r} != {theirs!r}"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy-path", type=Path, required=True)
    parser.add_argument("--output", type=Path, default=None)
    parser.add_argument("--check", type=Path, default=None, help="a committed run to compare with")
    args = parser.parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        flags = [f"--{name}={count}" for name, count in COUNTS.items()]
        command = [
            sys.executable,
            "-m",
            "lerobot_suture.cli",
            "experiments",
            f"--policy.path={args.policy_path}",
            f"--output_dir={tmp}",
            "--workers=1",
            *flags,
        ]
        env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
        subprocess.run(command, check=True, env=env, stdout=subprocess.DEVNULL)
        found = {**outcomes(Path(tmp)), "leaderboard": leaderboard_outcomes(args.policy_path)}
    report = {
        "benchmark": "episode_outcomes",
        "policy": str(args.policy_path),
        "counts": {**COUNTS, "leaderboard_episodes": LEADERBOARD_EPISODES},
        "machine": machine(),
        "wall_s": round(time.perf_counter() - start, 1),
        "outcomes": found,
    }
    if args.check is not None:
        committed = json.loads(args.check.read_text())["outcomes"]
        found = differences(report["outcomes"], committed)
        report["check"] = {"against": str(args.check), "unchanged": not found, "differences": found[:50]}
    emit(report, args.output)
    if args.check is not None and found:
        sys.exit(1)


if __name__ == "__main__":
    main()
