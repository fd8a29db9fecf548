"""``lerobot-suture robustness-report``: policies side by side under the shifts, inside and beyond their
training ranges, with the gate (:mod:`lerobot_suture_studies.robustness`)."""

from __future__ import annotations

import draccus

from lerobot_suture_studies.robustness import RobustnessReportConfig, build_report


def main(argv: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=RobustnessReportConfig, args=argv, exit_on_error=False)
    build_report(cfg)
    print((cfg.output_dir / "robustness.md").read_text())
