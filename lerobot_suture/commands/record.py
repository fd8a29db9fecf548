"""``lerobot-suture record``: expert insertions recorded as a LeRobotDataset
(:mod:`lerobot_suture.datasets.record`).

Exit status (set by :mod:`lerobot_suture.cli`): 0 done; 2 bad flags or root; 1 a failed push; 128 + the
signal's number when interrupted (130 for Ctrl-C), with every finished episode kept.
"""

from __future__ import annotations

import contextlib
import logging

from lerobot_suture.datasets.record import record
from lerobot_suture.datasets.record_config import parse_config


def main(argv: list[str] | None = None) -> None:
    logging.getLogger("lerobot.configs.video").setLevel(logging.WARNING)  # "Using video codec" per file
    with contextlib.suppress(ImportError):  # FFmpeg's own INFO lines ("Starting second pass ...")
        import av.logging

        av.logging.set_level(av.logging.ERROR)
    record(parse_config(argv))
