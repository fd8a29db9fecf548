"""``lerobot-suture calibrate-stac --policy.path=DIR``: fit the STAC gate of a chunking LeRobot policy (ACT,
diffusion, ...) on nominal rollouts (:mod:`lerobot_suture.runtime.calibration` says how)."""

from __future__ import annotations

import draccus

from lerobot_suture.runtime.calibration import CalibrateStacConfig, run_stac_calibration


def main(argv: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=CalibrateStacConfig, args=argv, exit_on_error=False)
    report = run_stac_calibration(cfg)
    cal = report["calibration"]
    print(
        f"STAC gate calibrated on {cal['episodes']} nominal episodes ({cal['policy_type']}, bandwidth "
        f"{cal['bandwidth']}): per-episode threshold {cal['threshold']:.4g} at alpha {cal['alpha']}; "
        f"held-out false alarms {report['holdout_false_alarm_rate']:.3f} per episode."
    )
    print(f"Written: {report['calibration_file']}")
