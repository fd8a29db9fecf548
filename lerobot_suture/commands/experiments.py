"""``lerobot-suture experiments --policy.path=DIR``: the paper's experiments with a trained, calibrated
ensemble (:mod:`lerobot_suture.experiments.paper` says what runs)."""

from __future__ import annotations

import draccus

from lerobot_suture.experiments.paper import ExperimentsConfig, run_experiments


def main(argv: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=ExperimentsConfig, args=argv, exit_on_error=False)
    result = run_experiments(cfg)
    print((cfg.output_dir / "report.md").read_text())
    print(f"Figures, metrics.json and report.md in {cfg.output_dir} ({result['seconds']} s).")
