"""``lerobot-suture segment --source_root=DIR --subtask=insert``: one subtask's segments of recorded running
sutures as a dataset of their own (:mod:`lerobot_suture.datasets.segment`)."""

from __future__ import annotations

import draccus

from lerobot_suture.datasets.segment import SegmentConfig, segment_dataset


def main(argv: list[str] | None = None) -> None:
    cfg = draccus.parse(
        config_class=SegmentConfig, args=argv, prog="lerobot-suture segment", exit_on_error=False
    )
    summary = segment_dataset(cfg)
    print(
        f"{summary.num_episodes} {cfg.subtask} segments ({summary.num_frames} frames) in {summary.root}; "
        f"train: episodes {summary.train_episodes[0]}..{summary.train_episodes[-1]}"
        if summary.train_episodes
        else f"{summary.num_episodes} {cfg.subtask} segments in {summary.root}, all validation"
    )
