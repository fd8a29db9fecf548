#!/usr/bin/env python
"""Open-loop action error of trained ensemble checkpoints on the dataset's validation episodes.

How far along is the vision path? For each checkpoint, a fixed, seeded sample of validation frames
(with the observation and action windows the policy was trained on) goes through the checkpoint's own
pre-processor and the fused members; the members' mean chunk is compared with the expert's recorded
actions. Per checkpoint it prints one JSON line: the median jaw-position error (mm) of the first
executed action and of the last action of the chunk, and ``stay_mm``, the error of keeping the current
pose until the chunk's end: a policy that ignores the phantom's pose in the image scores about that.
The entry tolerance of the task is 2 mm.

    python studies/benchmarks/open_loop_error.py --dataset-root DIR CHECKPOINT [CHECKPOINT ...]

CHECKPOINT is a ``pretrained_model`` directory, or a run's ``checkpoints`` directory (every step in it).
``--episodes 1,2,3`` (or ``all``) reads those episodes instead of the validation split: e.g. a
``lerobot-suture dagger`` round's ``new_data`` (the surgeon's segments only; ``collect.json`` lists its runs,
those with surgeon steps in order), to ask whether a fine-tuned ensemble reproduces the labels it was
trained on, and the next round's, which it was not. ``--frame-bins 0,3,8`` adds the first action's error
by frame index (in a surgeon segment: frames since the takeover).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from lerobot_suture.datasets.split import validation_episodes  # noqa: E402
from lerobot_suture.runtime.policy import load_policy  # noqa: E402
from lerobot_suture.sim.task import TASK  # noqa: E402

NEEDS = "checkpoints and their dataset (CHECKPOINT ..., --dataset-root)"


def checkpoint_dirs(paths: list[str]) -> list[Path]:
    """``pretrained_model`` directories: given ones, and every step of a given ``checkpoints`` folder."""
    out = []
    for p in map(Path, paths):
        if (p / "config.json").is_file():
            out.append(p)
        elif p.is_dir():
            steps = sorted(d for d in p.iterdir() if d.name.isdigit() and (d / "pretrained_model").is_dir())
            if not steps:
                raise FileNotFoundError(f"No checkpoint in {p}: expected STEP/pretrained_model folders.")
            out += [d / "pretrained_model" for d in steps]
        else:
            raise FileNotFoundError(f"{p} is neither a pretrained_model directory nor a checkpoints folder.")
    return out


def frame_batch(
    dataset_root: Path, config, n_frames: int, seed: int, episodes: list[int] | None = None
) -> dict:
    """``n_frames`` frames of ``episodes`` (default: the validation split) with the observation and action
    windows of ``config``."""
    from lerobot.datasets import LeRobotDataset, LeRobotDatasetMetadata

    fps = LeRobotDatasetMetadata("local/eval", root=dataset_root).fps
    delta = {"action": [i / fps for i in config.action_delta_indices]}
    for key in config.input_features:
        delta[key] = [i / fps for i in config.observation_delta_indices]
    if episodes is None:
        episodes = validation_episodes(dataset_root)
        if not episodes:
            raise ValueError(f"The dataset at {dataset_root} has no validation episodes; pass --episodes.")
    dataset = LeRobotDataset("local/eval", root=dataset_root, episodes=episodes, delta_timestamps=delta)
    rng = np.random.default_rng(seed)
    indices = rng.choice(len(dataset), size=min(n_frames, len(dataset)), replace=False)
    items = [dataset[int(i)] for i in indices]
    batch = {
        k: torch.stack([it[k] for it in items]) for k in [*config.input_features, "action", "action_is_pad"]
    }
    batch["task"] = [TASK] * len(items)
    batch["frame_index"] = torch.stack([it["frame_index"] for it in items])
    return batch


def open_loop_error(
    checkpoint: Path,
    dataset_root: Path,
    n_frames: int,
    seed: int,
    device: str,
    episodes: list[int] | None = None,
    frame_bins: list[int] | None = None,
) -> dict:
    """The JSON line of one checkpoint (see the module docstring). ``frame_bins``: edges of frame-index
    bins (e.g. ``[0, 3, 8]``: frames 0-2, 3-7, 8 on) over which the first action's error is also given,
    median and mean, on every sampled frame (its first action never lies past the episode's end)."""
    policy, preprocessor, _ = load_policy(checkpoint, device)
    config = policy.config
    batch = frame_batch(dataset_root, config, n_frames, seed, episodes)
    expert = batch.pop("action")[..., :3]  # (B, T, 3) m
    pad = batch.pop("action_is_pad")  # (B, T)
    frame_index = batch.pop("frame_index").numpy()  # (B,)
    state = batch["observation.state"][:, -1, :3]  # (B, 3): the current jaw position
    policy.reset()
    started = time.perf_counter()
    with torch.inference_mode():
        generator = torch.Generator(device=device).manual_seed(seed)
        prediction = policy.predict_action_distribution(preprocessor(batch), generator=generator)
    mean = prediction.unnormalized.mean[..., :3].cpu()  # (B, T, 3) m
    first, last = config.n_obs_steps - 1, config.horizon - 1
    keep = ~pad[:, last]  # frames whose whole chunk lies inside the episode

    def median_mm(x: torch.Tensor) -> float:
        return round(float(x[keep].norm(dim=-1).median()) * 1e3, 3)

    result = {
        "checkpoint": str(checkpoint),
        "members": config.n_members,
        "frames": int(keep.sum()),
        "first_action_mm": median_mm(mean[:, first] - expert[:, first]),
        "last_action_mm": median_mm(mean[:, last] - expert[:, last]),
        "stay_mm": median_mm(state - expert[:, last]),
        "seconds": round(time.perf_counter() - started, 1),
    }
    if frame_bins:
        first_mm = (mean[:, first] - expert[:, first]).norm(dim=-1).numpy() * 1e3
        edges = [*frame_bins, np.inf]
        by_frame = {}
        for low, high in zip(edges[:-1], edges[1:], strict=True):
            in_bin = (frame_index >= low) & (frame_index < high)
            label = f"{low}-{high - 1}" if np.isfinite(high) else f"{low}-"
            by_frame[label] = {
                "frames": int(in_bin.sum()),
                "median_mm": round(float(np.median(first_mm[in_bin])), 3) if in_bin.any() else None,
                "mean_mm": round(float(np.mean(first_mm[in_bin])), 3) if in_bin.any() else None,
            }
        result["first_action_mm_by_frame"] = by_frame
    return result


def parse_episodes(text: str | None, dataset_root: Path) -> list[int] | None:
    """``--episodes``: None (the validation split), ``all``, or comma-separated indices."""
    if text is None:
        return None
    if text == "all":
        from lerobot.datasets import LeRobotDatasetMetadata

        return list(range(LeRobotDatasetMetadata("local/eval", root=dataset_root).total_episodes))
    try:
        return [int(e) for e in text.split(",")]
    except ValueError as err:
        raise SystemExit(
            f"--episodes must be 'all' or comma-separated integers, e.g. 1,2,3. Got {text!r}."
        ) from err


def parse_frame_bins(text: str | None) -> list[int] | None:
    """``--frame-bins``: increasing frame indices >= 0, comma-separated (None: no bins)."""
    if text is None:
        return None
    try:
        edges = [int(e) for e in text.split(",")]
    except ValueError as err:
        raise SystemExit(f"--frame-bins must be comma-separated integers, e.g. 0,3,8. Got {text!r}.") from err
    if edges[0] < 0 or any(b <= a for a, b in zip(edges, edges[1:], strict=False)):
        raise SystemExit(f"--frame-bins must increase from a frame index >= 0, e.g. 0,3,8. Got {text!r}.")
    return edges


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("checkpoints", nargs="+")
    parser.add_argument("--dataset-root", type=Path, required=True)
    parser.add_argument("--frames", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--episodes", default=None, help="comma-separated episode indices, or 'all'")
    parser.add_argument(
        "--frame-bins", default=None, help="frame-index bin edges for the first action's error, e.g. 0,3,8"
    )
    args = parser.parse_args()
    episodes = parse_episodes(args.episodes, args.dataset_root)
    bins = parse_frame_bins(args.frame_bins)
    for checkpoint in checkpoint_dirs(args.checkpoints):
        result = open_loop_error(
            checkpoint, args.dataset_root, args.frames, args.seed, args.device, episodes, bins
        )
        print(
            json.dumps({"benchmark": "open_loop_error", "episodes": args.episodes or "validation", **result}),
            flush=True,
        )


if __name__ == "__main__":
    main()
