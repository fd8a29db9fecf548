"""STAC gating a chunking LeRobot policy (ACT by default): per-episode AUROC and false alarms.

The policy (calibrated with ``lerobot-suture calibrate-stac``) is rolled out on ``--episodes`` fresh test seeds in
the nominal scenario and in each of ``--scenarios``; every chunk it predicts is scored by STAC against the one
before (the same capture and monitor ``lerobot-rollout --strategy.type=gated_dagger`` runs). An episode's score is
its maximum; AUROC is nominal vs perturbed episodes, with DeLong's 95% interval; false alarms are nominal
episodes whose maximum crosses the calibrated threshold. Bars: AUROC >= 0.9 on ``needle_drop`` and
``phantom_moved_after_insertion``; false alarms <= 5% per episode. Prints one JSON object.

    .venv/bin/python benchmarks/stac_gate.py --policy-path DIR [--episodes 50] [--output FILE]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
from _report import emit  # noqa: E402

from lerobot_suture.experiments.metrics import auroc, auroc_interval, wilson_interval  # noqa: E402
from lerobot_suture.runtime.calibration import stac_maxima  # noqa: E402
from lerobot_suture.runtime.gates import StacGates  # noqa: E402
from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy  # noqa: E402
from lerobot_suture.runtime.seeds import fresh_seeds  # noqa: E402
from lerobot_suture.safety.ood.calibration_file import StacCalibration  # noqa: E402

NEEDS = "a chunking policy calibrated by lerobot-suture calibrate-stac (--policy-path)"
SCENARIOS = ("needle_drop", "phantom_moved_after_insertion")
SEED_OFFSET = 500_000
AUROC_BAR, FALSE_ALARM_BAR = 0.9, 0.05


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy-path", type=Path, required=True)
    parser.add_argument("--episodes", type=int, default=50, help="per scenario, nominal included")
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS))
    parser.add_argument("--output", type=Path, default=None)
    args = parser.parse_args()

    calibration = StacCalibration.load(args.policy_path)
    runner = PolicyRunner.from_pretrained(args.policy_path, GateMode.REPORT)
    gates = StacGates(runner.policy, calibration)
    env_kwargs = env_kwargs_for_policy(runner.policy.config)
    seeds = fresh_seeds(args.episodes, start=SEED_OFFSET)
    report: dict = {
        "benchmark": "stac_gate",
        "policy": str(args.policy_path),
        "policy_type": calibration.policy_type,
        "calibration": calibration.__dict__,
        "seeds": [seeds[0], seeds[-1]],
    }
    start = time.perf_counter()
    maxima: dict[str, list[float]] = {}
    success: dict[str, list[bool]] = {}
    for scenario in ("nominal", *args.scenarios):
        try:
            scenario_maxima, logs = stac_maxima(runner, gates, env_kwargs, seeds, scenario, scenario)
        except KeyboardInterrupt:
            print(f"interrupted in {scenario}", file=sys.stderr)
            break
        maxima[scenario] = scenario_maxima.tolist()
        success[scenario] = [log.success for log in logs]
    nominal = maxima.get("nominal", [])
    alarms = sum(m > calibration.threshold for m in nominal)
    low, high = wilson_interval(alarms, len(nominal)) if nominal else (float("nan"), float("nan"))
    report["nominal"] = {
        "episodes": len(nominal),
        "success_rate": float(np.mean(success["nominal"])) if nominal else None,
        "false_alarms": alarms,
        "false_alarm_rate": round(alarms / len(nominal), 4) if nominal else None,
        "false_alarm_wilson95": [round(low, 4), round(high, 4)],
    }
    report["scenarios"] = {}
    for scenario in args.scenarios:
        if scenario not in maxima:
            continue
        flagged = sum(m > calibration.threshold for m in maxima[scenario])
        interval = auroc_interval(nominal, maxima[scenario])
        report["scenarios"][scenario] = {
            "episodes": len(maxima[scenario]),
            "success_rate": float(np.mean(success[scenario])),
            "auroc": round(auroc(nominal, maxima[scenario]), 4),
            "auroc_interval95": [round(float(v), 4) for v in interval],
            "flagged": flagged,
            "flagged_rate": round(flagged / len(maxima[scenario]), 4),
        }
    report["bar"] = {
        "auroc_min": AUROC_BAR,
        "false_alarm_max": FALSE_ALARM_BAR,
        "pass": bool(
            report["scenarios"]
            and all(s["auroc"] >= AUROC_BAR for s in report["scenarios"].values())
            and (report["nominal"]["false_alarm_rate"] or 0.0) <= FALSE_ALARM_BAR
        ),
    }
    report["wall_s"] = round(time.perf_counter() - start, 1)
    emit(report, args.output)


if __name__ == "__main__":
    main()
