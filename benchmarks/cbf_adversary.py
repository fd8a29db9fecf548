"""Adversarial episodes against the CBF on either path, harm counted at the physics rate wherever it happens.

For each condition (``lerobot_suture.experiments.attack_episodes.CONDITIONS``: tissue that stands still, is
servoed during the approach, moves after insertion, or breathes at the declared acceleration bound; every throw of a
four-throw running suture; on the robot path also an arm lagging 10, 20 or 30% in pose space and 0.3 s of
observation or command latency; and tissue moving beyond the declared bounds), ``--episodes-per-family`` episodes of
every attack family (``cbf_attacks.FAMILIES``). On the env path the ``still`` condition adds ``--policy-episodes``
of an ensemble pushed off distribution (an untrained tiny ensemble with the expert's statistics, or
``--policy-path``), taking over a begun throw in the ``camera_moved`` scenario, its gate not consulted.

A violation is a physics step at which the needle, held by the simulator's grasp, has its tip in the tissue
outside the wound's ellipsoid, counted over the whole episode whatever the filter says of its own state.
Bar: 0 violations in >= 1,000 episodes in every condition within the bounds. Beyond the bounds (measured): of the
episodes in which the tissue moved while the needle was held, the share the guard flagged, and how deep any
violation went.

Prints one JSON object (per condition: episodes, active steps, violations, min h below the surface, deepest
violation, flagged episodes, intervention rate; per family; on the env path tracking error and segment deviation
p50 / p99 / max and the filter's time per call). With ``--output`` the file is rewritten after every condition,
so an interrupted run keeps what it finished.

    .venv/bin/python benchmarks/cbf_adversary.py --path env [--conditions still,breathing_at_bound]
        [--episodes-per-family 100] [--beyond-episodes-per-family 20] [--policy-episodes 40] [--output FILE]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
from _attack_paths import make_path  # noqa: E402
from _report import emit, machine, write  # noqa: E402
from tqdm import tqdm  # noqa: E402

from lerobot_suture.experiments.attack_episodes import (  # noqa: E402
    CONDITIONS,
    POLICY_FAMILY,
    AttackEpisode,
    conditions_for,
    run_attack,
    run_policy_attack,
    summarize_attacks,
)
from lerobot_suture.experiments.cbf_attacks import FAMILIES  # noqa: E402
from lerobot_suture.safety.cbf_config import CBFConfig  # noqa: E402

BAR_EPISODES = 1000


def tiny_off_distribution_policy(directory: Path) -> Path:
    """An untrained tiny ensemble whose normalization comes from the expert's poses: its actions are in the
    right units and range, and it knows nothing of the task (off distribution everywhere)."""
    from _policy_builders import save_untrained_expert_policy

    return save_untrained_expert_policy(
        directory / "pretrained_model", n_members=2, num_inference_steps=3, noise_scheduler_type="DDIM"
    )


def quantiles_mm(values: list[float]) -> dict[str, float]:
    v = np.asarray([x for x in values if np.isfinite(x)]) * 1e3
    if v.size == 0:
        return {"p50": None, "p99": None, "max": None}
    return {
        "p50": round(float(np.median(v)), 4),
        "p99": round(float(np.percentile(v, 99)), 4),
        "max": round(float(v.max()), 4),
    }


def summarize(episodes: list[AttackEpisode]) -> dict:
    report = summarize_attacks(episodes)
    times = [t for e in episodes for t in e.filter_times if np.isfinite(t)]
    if times:
        report["tracking_error_mm"] = quantiles_mm([x for e in episodes for x in e.tracking_errors])
        report["segment_deviation_mm"] = quantiles_mm([x for e in episodes for x in e.segment_deviations])
        report["filter_time_us"] = {
            "p50": round(float(np.median(times)) * 1e6, 2),
            "mean": round(float(np.mean(times)) * 1e6, 2),
            "worst": round(float(np.max(times)) * 1e6, 2),
        }
    return report


def run_condition(path_name: str, condition: str, seeds: range, args, config, progress, tmp: Path) -> dict:
    """Every family on ``seeds`` in ``condition`` (and the policy family where it applies)."""
    spec = CONDITIONS[condition]
    episodes: list[AttackEpisode] = []
    path = make_path(path_name, condition, config)
    interrupted = False
    try:
        for seed in seeds:
            for family in FAMILIES:
                episodes.append(run_attack(path, family, seed, spec.throw(seed), args.attack_steps))
                progress.update()
        if path_name == "env" and condition == "still" and args.policy_episodes:
            from lerobot_suture.runtime.policy import GateMode, PolicyRunner

            policy = args.policy_path or tiny_off_distribution_policy(tmp)
            runner = PolicyRunner.from_pretrained(policy, GateMode.REPORT)
            for seed in range(args.first_seed, args.first_seed + args.policy_episodes):
                episodes.append(run_policy_attack(runner, seed, "camera_moved", config, args.attack_steps))
                progress.update()
    except KeyboardInterrupt:
        interrupted = True
    finally:
        path.close()
    block = {"condition": asdict(spec), **summarize(episodes)}
    families = (*FAMILIES, POLICY_FAMILY)
    block["families"] = {
        f: summarize([e for e in episodes if e.family == f])
        for f in families
        if any(e.family == f for e in episodes)
    }
    # Each harmful episode by (family, seed, throw), to replay it with run_attack.
    block["violating_episodes"] = [[e.family, e.seed, e.throw] for e in episodes if e.violation_steps]
    if spec.within_bounds:
        block["bar"] = {
            "episodes_min": BAR_EPISODES,
            "pass": block["episodes"] >= BAR_EPISODES and block["violations"]["physics_steps"] == 0,
        }
    else:
        moved = [e for e in episodes if e.moved_while_held]
        flagged = sum(e.motion_flagged for e in moved)
        block["flagged_share_of_moved"] = round(flagged / len(moved), 4) if moved else None
    if interrupted:
        block["interrupted"] = True
    return block


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--path", choices=("env", "robot"), default="env")
    parser.add_argument(
        "--conditions", default=None, help="comma-separated names (default: all for the path)"
    )
    parser.add_argument("--episodes-per-family", type=int, default=100)
    parser.add_argument("--beyond-episodes-per-family", type=int, default=20)
    parser.add_argument("--policy-episodes", type=int, default=40)
    parser.add_argument(
        "--policy-path", type=Path, default=None, help="a trained policy (default: tiny untrained)"
    )
    parser.add_argument("--attack-steps", type=int, default=30)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args()

    names = args.conditions.split(",") if args.conditions else conditions_for(args.path)
    unknown = [n for n in names if n not in conditions_for(args.path)]
    if unknown:
        parser.error(
            f"conditions {unknown} do not apply to the {args.path} path; it has {conditions_for(args.path)}"
        )
    config = CBFConfig(enabled=True)

    def per_family(name: str) -> int:
        return args.episodes_per_family if CONDITIONS[name].within_bounds else args.beyond_episodes_per_family

    total = sum(per_family(n) * len(FAMILIES) for n in names)
    if args.path == "env" and "still" in names:
        total += args.policy_episodes
    report: dict = {
        "benchmark": "cbf_adversary",
        "command": " ".join(["python", *sys.argv]),
        "path": args.path,
        "families": list(FAMILIES),
        "conditions": {},
    }
    report["cbf"] = asdict(config)
    start = time.perf_counter()
    progress = tqdm(total=total, desc=f"{args.path}-path attacks", unit="episode", file=sys.stderr)
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            seeds = range(args.first_seed, args.first_seed + per_family(name))
            block = run_condition(args.path, name, seeds, args, config, progress, Path(tmp))
            report["conditions"][name] = block
            bars = [b["bar"]["pass"] for b in report["conditions"].values() if "bar" in b]
            report["bar_pass"] = bool(bars) and all(bars)
            report["wall_s"] = round(time.perf_counter() - start, 1)
            report["machine"] = machine()
            if args.output is not None:
                write(report, args.output)
            if block.get("interrupted"):
                print(f"interrupted in condition {name}", file=sys.stderr)
                break
    progress.close()
    emit(report, args.output)


if __name__ == "__main__":
    main()
