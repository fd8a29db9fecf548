"""``lerobot-suture reproduce --recipe=NAME``: a recipe's reference from nothing, and its table beside the
committed one (:mod:`lerobot_suture.pipelines.reproduce`)."""

from __future__ import annotations

import draccus

from lerobot_suture.pipelines.reproduce import ReproduceConfig, run_reproduce


def main(argv: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=ReproduceConfig, args=argv, exit_on_error=False)
    print(run_reproduce(cfg))
    print(f"comparison.md, comparison.json and timings.json in {cfg.output_dir}")
