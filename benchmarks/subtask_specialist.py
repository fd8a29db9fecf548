"""A policy for one subtask of the running suture, trained on that subtask's segments alone.

Cuts a running-suture recording made with ``--subtask=true`` into the subtask's segments (``lerobot-suture
segment``: one episode per throw's segment, each in its suture's split), then trains the running suture's preset
(``policies/presets/running_suture.json``, its steps and batch, ``--members`` members) with the real
``lerobot-train`` on the training segments. The checkpoint joins a chain as that subtask's own policy
(``benchmarks/chain_cell.py --insert DIR``). Both stages are resumable, and each one's wall time is reported::

    .venv/bin/python benchmarks/subtask_specialist.py --source DIR --subtask insert --work-dir outputs/specialists
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from _report import emit, machine
from task_levers import _timed, train

NEEDS = "a running suture recorded with --subtask=true (--source DIR) and the subtask (--subtask)"


def main() -> None:
    from lerobot_suture.datasets.metadata import read_episode_log
    from lerobot_suture.datasets.segment import SegmentConfig, segment_dataset
    from lerobot_suture.sim.subtasks import SUBTASKS

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", type=Path, required=True, help="the running-suture recording")
    parser.add_argument("--subtask", choices=SUBTASKS, required=True)
    parser.add_argument(
        "--members", type=int, default=1, help="the ensemble's members (1: its member recipe)"
    )
    parser.add_argument("--work-dir", type=Path, required=True, help="segments and training (rerun: resume)")
    parser.add_argument("--output", type=Path)
    args = parser.parse_args()

    root = args.work_dir / "data" / args.subtask
    timing = args.work_dir / "data" / f"{args.subtask}.segment_s.json"
    if not root.is_dir():
        cfg = SegmentConfig(source_root=str(args.source), subtask=args.subtask, root=str(root))
        _timed(timing, "segment_s", lambda: segment_dataset(cfg))
    log = read_episode_log(root)
    out = args.work_dir / "train" / f"{args.subtask}_n{args.members}"
    pretrained, train_s = train("running_suture", root, out, args.members)
    lengths = [e["length"] for e in log["episodes"]]
    emit(
        {
            "subtask": args.subtask,
            "source": str(args.source),
            "segments": len(lengths),
            "training_segments": len(log["splits"]["train"]),
            "frames": sum(lengths),
            "frames_per_segment_median": sorted(lengths)[len(lengths) // 2],
            "members": args.members,
            "segment_s": round(json.loads(timing.read_text())["segment_s"], 1) if timing.is_file() else None,
            "train_s": round(train_s, 1),
            "pretrained": str(pretrained),
            "machine": machine(),
        },
        args.output,
    )


if __name__ == "__main__":
    main()
