"""``lerobot-suture teleop --teleop=keyboard|gamepad``: the env driven by hand
(:mod:`lerobot_suture.surgeon.run`)."""

from __future__ import annotations

import draccus

from lerobot_suture.surgeon.run import TeleopConfig, teleop


def main(argv: list[str] | None = None) -> None:
    teleop(draccus.parse(config_class=TeleopConfig, args=argv, exit_on_error=False))
