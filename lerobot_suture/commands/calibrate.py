"""``lerobot-suture calibrate --policy.path=DIR``: fit the O.O.D. gate of a trained ensemble
(:mod:`lerobot_suture.runtime.calibration` says how)."""

from __future__ import annotations

import draccus

from lerobot_suture.runtime.calibration import CalibrateConfig, run_calibration


def main(argv: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=CalibrateConfig, args=argv, exit_on_error=False)
    report = run_calibration(cfg)
    cal = report["calibration"]
    source = (
        f"{report['episodes']} recorded episodes at {report['rollouts']}"
        if "rollouts" in report
        else f"{len(report['calibration_seeds'])} nominal episodes"
    )
    print(
        f"O.O.D. gate calibrated on {cal['n_samples']} predictions of {source}: {cal['model']} model, "
        f"mean {cal['mean']:.4g}, std {cal['std']:.4g}, h {cal['h']}, "
        f"mode {cal['mode']}, alpha {cal['alpha']} -> threshold {cal['threshold']:.4g} "
        f"({cal['score_name']}, {cal['space']} space)."
    )
    if "holdout_false_alarm_rate" in report:
        rates = report["holdout_false_alarm_rate"]
        print(
            f"False alarms on {rates['n_episodes']} held-out nominal episodes: {rates['per_step']:.3f} per "
            f"prediction, {rates['per_episode']:.3f} per episode."
        )
    print(f"Written: {report['calibration_file']}")
