"""``lerobot-suture segment``: one subtask of recorded running sutures, each of its segments an episode.

A running suture recorded with ``--subtask=true`` carries the high level's subtask and throw in every frame
(``observation.environment_state``, after the marks: the rules of :mod:`lerobot_suture.sim.subtasks` on the
measured pose, the labels the chain acts on). This cuts every suture into the runs of one subtask
(``--subtask=insert``: each throw's insert, with the first frames of what follows: ``tail_frames``) and writes
each run as an episode of a new LeRobotDataset (v3.0, the same features and fps; videos decoded and encoded again
by LeRobot's own recorder), so a policy for that subtask alone trains on it with ``lerobot-train`` and joins the
chain (``lerobot-suture chain --insert=DIR``).
A policy trained on whole sutures draws most of its batches from the subtasks that last longest; one trained on
the segments spends its whole budget on its subtask::

    lerobot-suture segment --source_root=data/suture_running --subtask=insert --root=data/suture_running_insert

Each segment keeps the split of the suture it was cut from (no validation suture leaks into training); the
episode log (``meta/suture_episodes.json``) names each segment's suture (``source_episode``, its ``seed``), its
``throw`` and its ``from_frame``. The new dataset is written beside ``root`` and moved there only when complete,
and the source is only read: an interrupted run loses nothing and a rerun starts over.
"""

from __future__ import annotations

import copy
import itertools
import logging
import math
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lerobot_suture.datasets import metadata
from lerobot_suture.datasets.features import ENV_STATE_KEY
from lerobot_suture.datasets.split import TRAIN, VAL, info_splits
from lerobot_suture.sim.subtasks import SUBTASK_NAMES, SUBTASKS

logger = logging.getLogger(__name__)

LEROBOT_COLUMNS = ("timestamp", "frame_index", "episode_index", "index", "task_index")
"""The columns LeRobot writes itself (``DEFAULT_FEATURES``): not a frame's content."""


@dataclass
class SegmentConfig:
    """Args:
    source_root: a dataset recorded by ``lerobot-suture record --task=running_suture --subtask=true``.
    subtask: the subtask to keep, one of ``insert``, ``extract``, ``lay_down``, ``pick_up``.
    repo_id: the new dataset's id (default: the source's with ``_SUBTASK`` appended).
    root: where to write it; must not exist (default: ``source_root`` with ``_SUBTASK`` appended).
    min_frames: shorter segments are left out, >= 1.
    tail_frames: frames of what follows kept after each segment, >= 0. A subtask ends on an action whose effect
        the rules read a frame later (the insert's last action opens the jaw); LeRobot starts no training sample
        in an episode's last ``drop_n_last_frames`` (4 in the presets), so without a tail of as many frames the
        action that ends the subtask is never a sample's first action, and the policy never takes it.
    """

    source_root: str = ""
    subtask: str = "insert"
    repo_id: str | None = None
    root: str | None = None
    min_frames: int = 1
    tail_frames: int = 4

    def __post_init__(self) -> None:
        if not self.source_root:
            raise ValueError(
                "`source_root` is required: pass --source_root=DIR, a running suture recorded with "
                "`lerobot-suture record --task=running_suture --subtask=true`."
            )
        if self.subtask not in SUBTASKS:
            raise ValueError(f"`subtask` must be one of {list(SUBTASKS)}. Got {self.subtask!r}.")
        if self.min_frames < 1:
            raise ValueError(f"`min_frames` must be >= 1. Got {self.min_frames}.")
        if self.tail_frames < 0:
            raise ValueError(f"`tail_frames` must be >= 0. Got {self.tail_frames}.")

    def output_root(self) -> Path:
        return Path(self.root if self.root is not None else f"{self.source_root.rstrip('/')}_{self.subtask}")

    def command(self) -> str:
        """The command that writes this dataset (every flag spelled out)."""
        flags = [
            f"--source_root={self.source_root}",
            f"--subtask={self.subtask}",
            f"--root={self.output_root()}",
        ]
        if self.repo_id is not None:
            flags.append(f"--repo_id={self.repo_id}")
        if self.min_frames != 1:
            flags.append(f"--min_frames={self.min_frames}")
        if self.tail_frames != 4:
            flags.append(f"--tail_frames={self.tail_frames}")
        return "lerobot-suture segment " + " ".join(flags)


@dataclass
class SegmentSummary:
    repo_id: str
    root: Path
    num_episodes: int
    num_frames: int
    train_episodes: list[int]
    val_episodes: list[int]
    seconds: float


def subtask_runs(environment_state: np.ndarray, names: list[str], subtask: str) -> list[tuple[int, int, int]]:
    """The maximal runs of ``subtask`` in one suture's frames, as ``(start, stop, throw)`` (``stop`` exclusive).

    Args:
        environment_state: (T, D) the frames' environment state, whose columns ``names`` include
            :data:`~lerobot_suture.sim.subtasks.SUBTASK_NAMES` (one-hot subtask, then the 0-based throw).
        names: the feature's column names.
        subtask: one of :data:`~lerobot_suture.sim.subtasks.SUBTASKS`.
    """
    columns = [names.index(name) for name in SUBTASK_NAMES]
    labels = np.asarray(environment_state)[:, columns]
    inside = labels[:, SUBTASKS.index(subtask)] > 0.5
    # A run ends where the subtask does, or where the throw changes under it: -1 marks frames outside it.
    throw_inside = np.where(inside, np.rint(labels[:, -1]).astype(int), -1)
    runs, start = [], 0
    for throw, frames in itertools.groupby(throw_inside):
        stop = start + len(list(frames))
        if throw >= 0:
            runs.append((start, stop, int(throw)))
        start = stop
    return runs


def subtask_durations(source_root: str | Path, split: str = TRAIN) -> dict[str, list[int]]:
    """Each subtask's run lengths (frames, one per control step) in the ``split`` sutures of a running suture
    recorded with ``--subtask=true``: every recorded suture is the expert's and succeeded, so these are the
    successful segments a stage's time budget is fitted on (``stage_gate.fit_stage_budgets``).

    Raises:
        FileNotFoundError: ``source_root`` holds no dataset recorded by ``lerobot-suture record``.
        ValueError: the dataset does not record the subtask.
    """
    import pandas as pd

    root = Path(source_root).expanduser()
    log = metadata.read_episode_log(root)
    names = _check_source(root, metadata.read_json(root / metadata.INFO_PATH)["features"])
    wanted = set(log["splits"][split])
    frames = pd.concat(
        pd.read_parquet(path, columns=["episode_index", "frame_index", ENV_STATE_KEY])
        for path in sorted((root / "data").glob("*/*.parquet"))
    )
    durations: dict[str, list[int]] = {subtask: [] for subtask in SUBTASKS}
    for episode, rows in frames.groupby("episode_index"):
        if int(episode) not in wanted:
            continue
        state = np.stack(rows.sort_values("frame_index")[ENV_STATE_KEY].to_numpy())
        for subtask in SUBTASKS:
            durations[subtask] += [stop - start for start, stop, _ in subtask_runs(state, names, subtask)]
    return {subtask: values for subtask, values in durations.items() if values}


def eval_split_fraction(n_val: int, n: int) -> float:
    """A ``--dataset.eval_split`` fraction that holds out exactly the last ``n_val`` of ``n`` episodes (LeRobot
    holds out the last ``ceil(n * fraction)``), to four decimals."""
    for fraction in (round(n_val / n, 4), round((n_val - 0.5) / n, 4)):
        if math.ceil(n * fraction) == n_val:
            return fraction
    raise ValueError(f"No four-decimal fraction holds out {n_val} of {n} episodes.")


def _check_source(root: Path, info_features: dict) -> list[str]:
    """The names of the source's environment state; refuses a dataset without the subtask."""
    names = list((info_features.get(ENV_STATE_KEY) or {}).get("names") or [])
    if not all(name in names for name in SUBTASK_NAMES):
        raise ValueError(
            f"{root} does not record the subtask (no {list(SUBTASK_NAMES)} in {ENV_STATE_KEY}): record the "
            "running suture with `lerobot-suture record --task=running_suture --marks=true --subtask=true`."
        )
    return names


def segment_dataset(cfg: SegmentConfig) -> SegmentSummary:
    """Write the dataset ``cfg`` describes (see the module docstring).

    Raises:
        FileNotFoundError: ``source_root`` holds no dataset recorded by ``lerobot-suture record``.
        FileExistsError: ``root`` exists.
        ValueError: the source does not record the subtask, or holds no segment of it.
    """
    started = time.perf_counter()
    source_root = Path(cfg.source_root).expanduser()
    log = metadata.read_episode_log(source_root)
    source_info = metadata.read_json(source_root / metadata.INFO_PATH)
    names = _check_source(source_root, source_info["features"])
    root = cfg.output_root().expanduser()
    if root.exists():
        raise FileExistsError(
            f"{root} exists: remove it, or pass another --root for the {cfg.subtask} segments."
        )
    repo_id = cfg.repo_id or f"{log['repo_id']}_{cfg.subtask}"

    import datasets as hf_datasets
    from lerobot.datasets.io_utils import write_info
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.datasets.video_utils import decode_video_frames
    from tqdm import tqdm

    from lerobot_suture.datasets.card import write_dataset_card
    from lerobot_suture.datasets.scheduling import normal_scheduling
    from lerobot_suture.datasets.video import resolve_video_backend

    backend = resolve_video_backend()
    source = LeRobotDataset(log["repo_id"], root=source_root, video_backend=backend)
    features = {
        key: {
            k: (tuple(v) if k == "shape" else v)
            for k, v in feature.items()
            if k in ("dtype", "shape", "names")
        }
        for key, feature in source.meta.features.items()
        if key not in LEROBOT_COLUMNS
    }
    video_keys = list(source.meta.video_keys)
    tasks = {
        int(i): str(t) for t, i in zip(source.meta.tasks.index, source.meta.tasks["task_index"], strict=True)
    }
    partial = root.with_name(f".{root.name}.partial")
    shutil.rmtree(partial, ignore_errors=True)  # what an interrupted run left
    os.environ.setdefault("SVT_LOG", "1")
    dataset = LeRobotDataset.create(
        repo_id,
        source.fps,
        features,
        root=partial,
        robot_type=source.meta.robot_type,
        use_videos=bool(video_keys),
        video_backend=backend,
    )
    hf_datasets.disable_progress_bars()
    source_split = {i: TRAIN for i in log["splits"][TRAIN]} | {i: VAL for i in log["splits"][VAL]}
    episodes, splits = [], {TRAIN: [], VAL: []}
    order = [*log["splits"][TRAIN], *log["splits"][VAL]]  # train segments first: LeRobot's split is the tail
    for ep in tqdm(order, desc=f"{cfg.subtask} segments of sutures", unit="suture"):
        meta = source.meta.episodes[ep]
        rows = source.hf_dataset[int(meta["dataset_from_index"]) : int(meta["dataset_to_index"])]
        columns = {
            key: np.stack([np.asarray(v) for v in rows[key]]).reshape(-1, *features[key]["shape"])
            for key in features
            if key not in video_keys
        }
        for start, stop, throw in subtask_runs(columns[ENV_STATE_KEY], names, cfg.subtask):
            if stop - start < cfg.min_frames:
                continue
            stop = min(stop + cfg.tail_frames, len(columns[ENV_STATE_KEY]))
            frames = {key: values[start:stop] for key, values in columns.items()}
            for key in video_keys:
                timestamps = [
                    float(meta[f"videos/{key}/from_timestamp"]) + float(t)
                    for t in rows["timestamp"][start:stop]
                ]
                video = decode_video_frames(
                    source.root / source.meta.get_video_file_path(ep, key),
                    timestamps,
                    source.tolerance_s,
                    backend,
                    return_uint8=True,
                )
                frames[key] = video.permute(0, 2, 3, 1).numpy()  # (T, H, W, C), as recorded
            for t in range(stop - start):
                frame = {key: values[t] for key, values in frames.items()}
                dataset.add_frame({**frame, "task": tasks[int(rows["task_index"][start + t])]})
            with normal_scheduling():
                dataset.save_episode()
            split = source_split[ep]
            splits[split].append(len(episodes))
            episodes.append(
                {
                    "episode_index": len(episodes),
                    "seed": int(log["episodes"][ep]["seed"]),
                    "source_episode": int(ep),
                    "throw": throw,
                    "from_frame": start,
                    "length": stop - start,
                }
            )
    if not episodes:
        shutil.rmtree(partial, ignore_errors=True)
        raise ValueError(
            f"No {cfg.subtask} segment of at least {cfg.min_frames} frames in {source_root}: lower --min_frames "
            "or segment a running suture."
        )
    with normal_scheduling():
        dataset.finalize()
    dataset.meta.info.splits = info_splits(splits[TRAIN], splits[VAL])
    write_info(dataset.meta.info, partial)
    segment_log = copy.deepcopy(log)
    segment_log.update(
        repo_id=repo_id,
        episodes=episodes,
        splits=splits,
        discarded=[],
        val_fraction=eval_split_fraction(len(splits[VAL]), len(episodes)),
        command=cfg.command(),
        segment={
            "subtask": cfg.subtask,
            "tail_frames": cfg.tail_frames,
            "source_root": str(source_root),
            "source_repo_id": log["repo_id"],
        },
    )
    metadata.write_episode_log(partial, segment_log)
    write_dataset_card(partial)
    os.replace(partial, root)
    summary = SegmentSummary(
        repo_id=repo_id,
        root=root,
        num_episodes=len(episodes),
        num_frames=sum(e["length"] for e in episodes),
        train_episodes=splits[TRAIN],
        val_episodes=splits[VAL],
        seconds=time.perf_counter() - started,
    )
    logger.info(
        "%d %s segments (%d frames) of %d sutures in %s (%.0f s); train with --dataset.episodes=[0..%d]",
        summary.num_episodes,
        cfg.subtask,
        summary.num_frames,
        len(order),
        root,
        summary.seconds,
        len(splits[TRAIN]) - 1,
    )
    return summary
