"""``lerobot-suture demo``: the main job at a small default (:mod:`lerobot_suture.pipelines.demo`)."""

from __future__ import annotations

import draccus

from lerobot_suture.pipelines.demo import DemoConfig, run_demo


def main(argv: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=DemoConfig, args=argv, exit_on_error=False)
    summary = run_demo(cfg)
    for name, entry in summary["scenarios"].items():
        print(f"{name:32s} expert success {entry['success_rate']:.2f}  strip: {entry['strip']}")
    if "dataset" in summary:
        d = summary["dataset"]
        print(f"dataset {d['repo_id']}: {d['episodes']} episodes, {d['frames']} frames at {d['root']}")
    if "experiments" in summary:
        print(f"toy ensemble: {summary['policy']}")
        print(f"experiment figures, metrics.json and report.md: {summary['experiments']['dir']}")
        for figure in summary["experiments"]["figures"]:
            print(f"  {figure}")
    print(f"summary: {summary['path']}")
