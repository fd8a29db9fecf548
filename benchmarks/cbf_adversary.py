"""Adversarial episodes against the CBF safety filter, h read at the physics rate.

Runs ``--episodes-per-family`` episodes of every scripted attack family
(``lerobot_suture.experiments.cbf_attacks.FAMILIES``) and ``--policy-episodes`` of an ensemble policy pushed
off distribution: an untrained tiny ensemble with the expert's statistics (``--policy-path`` for a
trained one), taking over a begun throw in the ``camera_moved`` scenario with its gate not consulted.
Prints one JSON object: episodes; active steps; violations (episodes, and physics steps with h < 0 while
the filter was active); min h; intervention rate; tracking error and segment deviation p50 / p99 / max
(mm); mean and worst filter time per call (us). Bar: 0 violations in >= 1,000 episodes.

    .venv/bin/python benchmarks/cbf_adversary.py [--episodes-per-family 125] [--policy-episodes 40]

Ctrl-C stops early and still prints what was finished.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
from _report import emit, machine  # noqa: E402
from tqdm import tqdm  # noqa: E402

from lerobot_suture.experiments.cbf_attacks import (  # noqa: E402
    FAMILIES,
    POLICY_FAMILY,
    AttackEpisode,
    run_attack_episode,
    run_policy_attack_episode,
    summarize_attacks,
)
from lerobot_suture.safety.cbf_config import CBFConfig  # noqa: E402

BAR_EPISODES = 1000


def tiny_off_distribution_policy(directory: Path) -> Path:
    """An untrained tiny ensemble whose normalization comes from the expert's poses: its actions are in the
    right units and range, and it knows nothing of the task (off distribution everywhere)."""
    from lerobot_policy_ensemble_diffusion.testing import save_untrained_expert_policy

    return save_untrained_expert_policy(
        directory / "pretrained_model", n_members=2, num_inference_steps=3, noise_scheduler_type="DDIM"
    )


def quantiles_mm(values: list[float]) -> dict[str, float]:
    v = np.asarray([x for x in values if np.isfinite(x)]) * 1e3
    if v.size == 0:
        return {"p50": float("nan"), "p99": float("nan"), "max": float("nan")}
    return {
        "p50": round(float(np.median(v)), 4),
        "p99": round(float(np.percentile(v, 99)), 4),
        "max": round(float(v.max()), 4),
    }


def summarize(episodes: list[AttackEpisode], config: CBFConfig) -> dict:
    times = [t for e in episodes for t in e.filter_times if np.isfinite(t)]
    return {
        **summarize_attacks(episodes),
        "tracking_error_mm": quantiles_mm([x for e in episodes for x in e.tracking_errors]),
        "segment_deviation_mm": quantiles_mm([x for e in episodes for x in e.segment_deviations]),
        "margin_mm": config.margin * 1e3,
        "filter_time_us": {
            "p50": round(float(np.median(times)) * 1e6, 2) if times else None,
            "mean": round(float(np.mean(times)) * 1e6, 2) if times else None,
            "worst": round(float(np.max(times)) * 1e6, 2) if times else None,
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes-per-family", type=int, default=125)
    parser.add_argument("--policy-episodes", type=int, default=40)
    parser.add_argument(
        "--policy-path", type=Path, default=None, help="a trained policy (default: tiny untrained)"
    )
    parser.add_argument("--scenario", default="camera_moved", help="the policy family's perturbation")
    parser.add_argument("--attack-steps", type=int, default=30)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args()

    config = CBFConfig(enabled=True)
    seeds = range(args.first_seed, args.first_seed + args.episodes_per_family)
    jobs = [(family, seed) for seed in seeds for family in FAMILIES]
    jobs += [(POLICY_FAMILY, seed) for seed in range(args.first_seed, args.first_seed + args.policy_episodes)]
    episodes: list[AttackEpisode] = []
    runner = None
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        try:
            for family, seed in tqdm(jobs, desc="attacks", unit="episode", file=sys.stderr):
                if family == POLICY_FAMILY:
                    if runner is None:
                        from lerobot_suture.runtime.policy import GateMode, PolicyRunner

                        path = args.policy_path or tiny_off_distribution_policy(Path(tmp))
                        runner = PolicyRunner.from_pretrained(path, GateMode.REPORT)
                    episodes.append(
                        run_policy_attack_episode(runner, seed, args.scenario, config, args.attack_steps)
                    )
                else:
                    episodes.append(run_attack_episode(family, seed, config, args.attack_steps))
        except KeyboardInterrupt:
            print(f"interrupted after {len(episodes)} of {len(jobs)} episodes", file=sys.stderr)
    report = {"benchmark": "cbf_adversary", **summarize(episodes, config)}
    report["bar"] = {
        "episodes_min": BAR_EPISODES,
        "pass": report["episodes"] >= BAR_EPISODES and report["violations"]["physics_steps"] == 0,
    }
    report["families"] = {
        family: summarize([e for e in episodes if e.family == family], config)
        for family in (*FAMILIES, POLICY_FAMILY)
        if any(e.family == family for e in episodes)
    }
    report["policy"] = (
        str(args.policy_path) if args.policy_path else "tiny untrained ensemble, expert statistics"
    )
    report["policy_scenario"] = args.scenario
    report["wall_s"] = round(time.perf_counter() - start, 1)
    report["machine"] = machine()
    emit(report, args.output)


if __name__ == "__main__":
    main()
