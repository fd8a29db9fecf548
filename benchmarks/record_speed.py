"""Recording speed of ``lerobot-suture record``: frames/s, s per episode, bytes per episode, with and
without video encoding, and the projected time of the default 133-episode dataset.

Prints JSON. Target: the default 133 episodes (96 px, video) recorded in <= 10 minutes on the
2-core machine. Each configuration records ``--episodes`` episodes into a fresh temporary root through
``record()`` itself (rollout, PNG staging, AV1 encoding, parquet, checkpoints, card), after one warm-up
run so imports and encoder start-up are not counted; the one-off start-up (imports, first dataset)
is measured apart and added to the projection.

    python benchmarks/record_speed.py --episodes=6
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

DEFAULT_EPISODES = 133
BAR_S = 600.0


def _disk_bytes(root: Path) -> int:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file())


def _quiet_tqdm() -> None:
    """Progress bars off: they would land in the JSON's stream neighbours and cost a little time."""
    from functools import partialmethod

    from tqdm import tqdm

    tqdm.__init__ = partialmethod(tqdm.__init__, disable=True)


def _record(workdir: Path, name: str, episodes: int, video: bool, image_size: int) -> dict:
    from lerobot_suture.datasets.record import record
    from lerobot_suture.datasets.record_config import RecordConfig

    root = workdir / name
    cfg = RecordConfig(
        repo_id=f"bench/{name}",
        root=str(root),
        num_episodes=episodes,
        image_size=image_size,
        video=video,
        val_fraction=0.25 if episodes > 1 else 0.0,  # the recipes' split; one episode cannot be split
    )
    start = time.perf_counter()
    summary = record(cfg)
    seconds = time.perf_counter() - start
    size = _disk_bytes(root)
    return {
        "episodes": summary.num_episodes,
        "frames": summary.num_frames,
        "discarded": summary.discarded,
        "seconds": round(seconds, 3),
        "frames_per_s": round(summary.num_frames / seconds, 1),
        "s_per_episode": round(seconds / summary.num_episodes, 3),
        "bytes_per_episode": int(size / summary.num_episodes),
        "bytes_total": size,
    }


def _rollout_only(episodes: int, image_size: int) -> dict:
    """Env + expert alone (no dataset), to show where the time goes."""
    from lerobot_suture.datasets.expert_episode import expert_episode_frames, make_env
    from lerobot_suture.expert import ScriptedExpert

    env, expert = make_env("pixels_agent_pos", image_size, "nominal"), ScriptedExpert()
    expert_episode_frames(env, expert, seed=10_000)  # warm-up: renderer
    start, frames = time.perf_counter(), 0
    for seed in range(episodes):
        frames += expert_episode_frames(env, expert, seed).length
    seconds = time.perf_counter() - start
    env.close()
    return {"frames_per_s": round(frames / seconds, 1), "s_per_episode": round(seconds / episodes, 3)}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=6, help="episodes per configuration (default 6)")
    parser.add_argument("--image_size", type=int, default=96)
    args = parser.parse_args(argv)
    logging.disable(logging.INFO)
    _quiet_tqdm()

    t0 = time.perf_counter()
    import lerobot.datasets.lerobot_dataset  # noqa: F401  - the import a fresh CLI process pays

    import lerobot_suture.datasets.record  # noqa: F401

    imports_s = time.perf_counter() - t0
    workdir = Path(tempfile.mkdtemp(prefix="record_speed_"))
    try:
        t0 = time.perf_counter()
        _record(workdir, "warmup", 1, True, args.image_size)  # encoder, renderer, first-dataset set-up
        warmup_s = time.perf_counter() - t0
        with_video = _record(workdir, "video", args.episodes, True, args.image_size)
        without_video = _record(workdir, "images", args.episodes, False, args.image_size)
        rollout = _rollout_only(args.episodes, args.image_size)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)

    startup_s = imports_s + warmup_s - with_video["s_per_episode"]
    projected = startup_s + DEFAULT_EPISODES * with_video["s_per_episode"]
    result = {
        "benchmark": "record_speed",
        "machine": {
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "python": sys.version.split()[0],
        },
        "image_size": args.image_size,
        "episodes_per_config": args.episodes,
        "startup_s": round(startup_s, 2),
        "with_video": with_video,
        "without_video": without_video,
        "rollout_only": rollout,
        "projected_s_for_133_episodes_video": round(projected, 1),
        "projected_s_for_133_episodes_no_video": round(
            startup_s + DEFAULT_EPISODES * without_video["s_per_episode"], 1
        ),
        "projected_bytes_for_133_episodes_video": DEFAULT_EPISODES * with_video["bytes_per_episode"],
        "bar_s": BAR_S,
        "meets_bar": projected <= BAR_S,
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
