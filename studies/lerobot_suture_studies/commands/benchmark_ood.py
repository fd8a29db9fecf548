"""``lerobot-suture benchmark-ood --policy.path=DIR``: failure detectors, the gate's score and the field's,
compared on the same rollouts (:mod:`lerobot_suture_studies.benchmark_ood`)."""

from __future__ import annotations

import math

import draccus

from lerobot_suture_studies.benchmark_ood import BenchmarkOODConfig, run_benchmark
from lerobot_suture_studies.benchmark_ood_report import fmt


def main(argv: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=BenchmarkOODConfig, args=argv, exit_on_error=False)
    result = run_benchmark(cfg)
    aurocs = {n: r.get("mean_auroc_common_steps", math.nan) for n, r in result["detectors"].items()}
    ranked = sorted(aurocs, key=lambda n: -math.inf if math.isnan(aurocs[n]) else aurocs[n], reverse=True)
    print(
        "Mean AUROC over common steps: "
        + ", ".join(f"{n} {fmt(aurocs[n])}" for n in ranked)
        + f". Table: {cfg.output_dir / 'detectors.md'}"
    )
