"""``lerobot-suture surgeon-run --policy.path=DIR --surgeon=keyboard|gamepad|expert|none``: a policy run with a
surgeon taking over when the gate hands over (:mod:`lerobot_suture.surgeon.run`)."""

from __future__ import annotations

import draccus

from lerobot_suture.surgeon.run import SurgeonRunConfig, surgeon_run


def main(argv: list[str] | None = None) -> None:
    surgeon_run(draccus.parse(config_class=SurgeonRunConfig, args=argv, exit_on_error=False))
