"""``lerobot-suture dagger``: learning from the surgeon in rounds, uncertainty-gated DAgger beside ungated
DAgger and plain behaviour cloning (:mod:`lerobot_suture.dagger.loop`)."""

from __future__ import annotations

import draccus

from lerobot_suture.dagger.config import DaggerConfig
from lerobot_suture.dagger.loop import run_dagger


def main(argv: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=DaggerConfig, args=argv, exit_on_error=False)
    result = run_dagger(cfg)
    print(result["table"])
    print(f"dagger.md, dagger.json and dagger.png in {cfg.output_dir}")
