"""``lerobot-suture record``: scripted-expert needle insertions as a LeRobotDataset (format v3.0).

Rolls out :class:`~lerobot_suture.expert.ScriptedExpert` in ``lerobot_suture/NeedleInsertion-v0`` and
writes every successful episode with LeRobot's own recorder (``LeRobotDataset.create / add_frame /
save_episode / finalize``), at the env's control rate (10 fps):

======================================  ===========  ============================================
feature                                 shape        meaning
======================================  ===========  ============================================
``observation.images.endoscope``        (H, W, 3)    endoscope RGB (video, or PNG with --video=false)
``observation.state``                   (10,)        measured jaw-tip pose: x y z (m), first two
                                                     rotation columns, jaw closure
``observation.environment_state``       (18,)        privileged: entry, exit, needle centre (m),
                                                     needle rotation columns, needle tip (m);
                                                     only with ``--obs_type=pixels_agent_pos_state``
                                                     or ``state``
``observation.needle_keypoints``        (6,)         privileged: the needle's tip, middle and tail in
                                                     the endoscope image (x right, y down, in [-1, 1]);
                                                     a training target, never a policy input (image
                                                     datasets only)
``action``                              (10,)        target jaw-tip pose, same layout as the state
``next.reward`` / ``next.success`` /    (1,)         reward, success and episode end after the action
``next.done``
======================================  ===========  ============================================

Episode ``k`` of the recording attempts uses env seed ``seed + k``; failed attempts are discarded
(and logged with the reason), so kept episodes have increasing, not consecutive, seeds. Seeds,
split, discards and settings go to ``meta/suture_episodes.json`` (see
:mod:`lerobot_suture.datasets.metadata`); the split rule is in :mod:`lerobot_suture.datasets.split`.

Interrupting is safe: Ctrl-C or ``kill`` (SIGINT/SIGTERM) discards the episode in flight, finalizes
the dataset with every finished episode and exits; ``--resume=true`` continues to ``--num_episodes``.
A SIGKILL or power loss loses at most the episodes since the last checkpoint (``--checkpoint_every``);
``--resume=true`` rolls back to it first.

Example::

    lerobot-suture record --repo_id=$HF_USER/suture_expert --num_episodes=133 --val_fraction=0.25 \\
        --obs_type=pixels_agent_pos --image_size=96 --scenario=nominal --seed=0 --video=true
    lerobot-suture record --config_path=recipes/suture_expert.yaml --repo_id=$HF_USER/suture_expert
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import shutil
import time
from collections import Counter
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from lerobot_suture.datasets import metadata
from lerobot_suture.datasets.expert_episode import expert_episode_frames, make_env
from lerobot_suture.datasets.features import FPS, ROBOT_TYPE, dataset_features
from lerobot_suture.datasets.hub import check_hub_access, push_dataset
from lerobot_suture.datasets.record_config import RecordConfig
from lerobot_suture.datasets.resume import prepare_root
from lerobot_suture.datasets.scheduling import normal_scheduling
from lerobot_suture.datasets.split import info_splits, split_episodes
from lerobot_suture.datasets.stop_signals import RecordingInterrupted, StopSignals
from lerobot_suture.datasets.video import resolve_video_backend
from lerobot_suture.expert import ExpertConfig, ScriptedExpert

logger = logging.getLogger(__name__)

_MAX_DISCARD_RATIO = 1.0
"""A run stops when the attempts it discards exceed this fraction of --num_episodes (and 10)."""


def regenerate_episode(root: str | Path, episode_index: int) -> dict[str, np.ndarray]:
    """Re-run the expert with the seed of episode ``episode_index`` of the dataset at ``root``.

    Returns:
        The episode's non-video features stacked over frames (``{key: (T, ...)}``), images included
        (uncompressed, as rendered) when the dataset has them.

    Raises:
        RuntimeError: if the episode does not reproduce (a different length or no success).
    """
    log = metadata.read_episode_log(root)
    if "segment" in log:
        raise ValueError(
            f"{root} holds {log['segment']['subtask']} segments cut from the sutures of "
            f"{log['segment']['source_root']}: regenerate episode {log['episodes'][episode_index]['source_episode']} "
            "of that dataset instead."
        )
    entry = log["episodes"][episode_index]
    env = make_env(**log["env_kwargs"])
    try:
        rollout = expert_episode_frames(
            env,
            ScriptedExpert(ExpertConfig(**log["expert"]["config"])),
            entry["seed"],
            steps_after_success=log.get("steps_after_success", 0),
        )
    finally:
        env.close()
    if not rollout.success or rollout.length != entry["length"]:
        raise RuntimeError(
            f"Episode {episode_index} (seed {entry['seed']}) did not reproduce: recorded {entry['length']} "
            f"frames, success; regenerated {rollout.length} frames, success={rollout.success}. The env or "
            "expert changed since the dataset was recorded (see `versions` in its episode log)."
        )
    keys = [k for k in rollout.frames[0] if k != "task"]
    return {k: np.stack([f[k] for f in rollout.frames]) for k in keys}


# --------------------------------------------------------------------------------------------- record
@dataclass
class RecordSummary:
    """What a ``record`` run did."""

    repo_id: str
    root: Path
    num_episodes: int
    num_frames: int
    train_episodes: list[int]
    val_episodes: list[int]
    added_episodes: int
    discarded: int
    discard_reasons: dict[str, int]
    seconds: float
    pushed_url: str | None = None
    interrupted: bool = False
    video_backend: str | None = None


def _finish(dataset, root: Path, log: dict, cfg: RecordConfig) -> None:
    """Finalize; write split, episode log, card; mark the dataset clean."""
    from lerobot.datasets.io_utils import write_info

    from lerobot_suture.datasets.card import write_dataset_card

    with normal_scheduling():
        dataset.finalize()
    images = root / "images"  # LeRobot's frame staging area, left empty after video encoding
    if images.is_dir() and not any(p.is_file() for p in images.rglob("*")):
        shutil.rmtree(images)
    metadata.write_checkpoint(root, log)
    n = len(log["episodes"])
    val_fraction = cfg.val_fraction
    if n and math.ceil(n * val_fraction) == n:
        # Stopped before it holds enough episodes for its split (the config checked the finished one):
        # all train until a resumed recording finishes.
        val_fraction = 0.0
    train, val = split_episodes(n, val_fraction)
    log["val_fraction"] = val_fraction  # the card advertises --dataset.eval_split with it
    log["splits"] = {"train": train, "val": val}
    if log["episodes"]:  # the command that records exactly these episodes, so split, from scratch
        log["command"] = dataclasses.replace(cfg, num_episodes=n, val_fraction=val_fraction).command()
    dataset.meta.info.splits = info_splits(train, val)
    write_info(dataset.meta.info, root)
    metadata.write_episode_log(root, log)
    write_dataset_card(root)
    metadata.clear_checkpoint(root)


def record(cfg: RecordConfig) -> RecordSummary:
    """Record the dataset ``cfg`` describes (see the module docstring).

    Raises:
        FileExistsError: ``root`` exists and ``resume`` is false.
        FileNotFoundError: ``resume`` is true and there is nothing to resume.
        ValueError: ``resume`` with settings that differ from the recorded ones.
        lerobot_suture.datasets.hub.HubPushError: ``push_to_hub`` without a token or a reachable Hub
            (checked before recording), or the push failed (the local dataset is kept).
        RecordingInterrupted: Ctrl-C / kill; every finished episode was kept.
        RuntimeError: the expert failed on more attempts than ``num_episodes`` (and 10).
    """
    started = time.perf_counter()
    root = cfg.dataset_root()
    log, fresh = prepare_root(cfg, root)
    if cfg.push_to_hub:
        check_hub_access(cfg.repo_id)  # fail fast, before any recording

    import datasets as hf_datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from tqdm import tqdm

    os.environ.setdefault("SVT_LOG", "1")  # the AV1 encoder's banner, per episode, otherwise
    backend = resolve_video_backend() if cfg.video and cfg.has_images else None
    features = dataset_features(
        cfg.obs_type,
        cfg.image_size,
        cfg.video,
        cfg.wrist_camera,
        cfg.marks,
        cfg.subtask,
        cfg.relative_actions,
        cfg.regrasp_target,
    )
    expert = ScriptedExpert(ExpertConfig(**log["expert"]["config"]))
    env = make_env(
        cfg.obs_type,
        cfg.image_size,
        cfg.scenario,
        cfg.grasp,
        log["env_kwargs"].get("appearance"),
        log["env_kwargs"].get("task", "insertion"),
        log["env_kwargs"].get("wrist_camera", False),
        log["env_kwargs"].get("marks", False),
        log["env_kwargs"].get("subtask", False),
        log["env_kwargs"].get("relative_actions", False),
        log["env_kwargs"].get("regrasp_target", False),
        log["env_kwargs"].get("regrasp_from", "marks"),
    )
    bars_were_enabled = hf_datasets.is_progress_bar_enabled()
    hf_datasets.disable_progress_bars()  # a "Map" bar per saved episode otherwise

    def open_dataset(create: bool):
        if create:
            dataset = LeRobotDataset.create(
                cfg.repo_id,
                FPS,
                features,
                root=root,
                robot_type=ROBOT_TYPE,
                use_videos=cfg.video,
                video_backend=backend or "pyav",
            )
        else:
            dataset = LeRobotDataset.resume(cfg.repo_id, root=root, video_backend=backend or "pyav")
        hf_datasets.disable_progress_bars()  # LeRobot's metadata loading turns them back on
        return dataset

    n_before = len(log["episodes"])
    run = {
        "started": datetime.now(UTC).isoformat(timespec="seconds"),
        "command": cfg.command() + (" --resume=true" if cfg.resume else ""),
    }
    log["runs"].append(run)
    discarded_now: Counter[str] = Counter()
    max_discards = max(10, int(_MAX_DISCARD_RATIO * cfg.num_episodes))
    stops = StopSignals()
    dataset = None
    dirty = False  # an episode is half-saved
    interrupted: RecordingInterrupted | KeyboardInterrupt | None = None
    episode_bar = tqdm(total=cfg.num_episodes, initial=n_before, desc="episodes", unit="ep", position=0)
    frame_bar = tqdm(desc="frames", unit="frame", position=1, leave=False)
    try:
        with stops:
            with stops.deferred():
                dataset = open_dataset(fresh)
                metadata.write_checkpoint(root, log)
            since_checkpoint = 0
            while len(log["episodes"]) < cfg.num_episodes:
                seed = log["next_seed"]
                result = expert_episode_frames(
                    env,
                    expert,
                    seed,
                    on_step=frame_bar.update,
                    steps_after_success=log.get("steps_after_success", 0),
                )
                with stops.deferred():
                    log["next_seed"] = seed + 1
                    if not result.success:
                        discarded_now[result.reason] += 1
                        log["discarded"].append(
                            {
                                "seed": seed,
                                "reason": result.reason,
                                "detail": result.detail,
                                "steps": result.length,
                            }
                        )
                        episode_bar.set_postfix(discarded=sum(discarded_now.values()))
                        if sum(discarded_now.values()) > max_discards:
                            raise RuntimeError(
                                f"The expert failed on {sum(discarded_now.values())} attempts in scenario "
                                f"{cfg.scenario!r} (reasons: {dict(discarded_now)}); stopping with "
                                f"{len(log['episodes'])} episodes kept. Record expert data in a scenario the "
                                "expert solves (--scenario=nominal)."
                            )
                        continue
                    dirty = True
                    for frame in result.frames:
                        dataset.add_frame(frame)
                    with normal_scheduling():  # the video encoder may leave the thread real-time
                        dataset.save_episode()
                    info = result.info
                    log["episodes"].append(
                        {
                            "episode_index": len(log["episodes"]),
                            "seed": seed,
                            "length": result.length,
                            "entry_error_m": float(info["entry_error_m"]),
                            "exit_error_m": float(info["exit_error_m"]),
                            "protrusion_m": float(info["protrusion_m"]),
                            "tissue_strain": float(info["tissue_strain"]),
                        }
                    )
                    dirty = False
                    since_checkpoint += 1
                    if since_checkpoint >= cfg.checkpoint_every and len(log["episodes"]) < cfg.num_episodes:
                        with normal_scheduling():
                            dataset.finalize()
                        metadata.write_checkpoint(root, log)
                        dataset = open_dataset(False)
                        since_checkpoint = 0
                episode_bar.update(1)
    except KeyboardInterrupt as exc:  # RecordingInterrupted included
        interrupted = exc
    finally:
        stops.stopping = True
        frame_bar.close()
        episode_bar.close()
        env.close()
        if bars_were_enabled:
            hf_datasets.enable_progress_bars()
        if dataset is not None and not dirty:
            run.update(
                finished=datetime.now(UTC).isoformat(timespec="seconds"),
                episodes_added=len(log["episodes"]) - n_before,
                discarded=sum(discarded_now.values()),
                interrupted=interrupted is not None,
            )
            with stops:
                _finish(dataset, root, log, cfg)
        elif dirty:
            logger.error(
                "Stopped while saving an episode: %s keeps its last checkpoint; `--resume=true` rolls "
                "back to it and continues.",
                root,
            )

    n_total = len(log["episodes"])
    summary = RecordSummary(
        repo_id=cfg.repo_id,
        root=root,
        num_episodes=n_total,
        num_frames=sum(e["length"] for e in log["episodes"]),
        train_episodes=list(log["splits"]["train"]),
        val_episodes=list(log["splits"]["val"]),
        added_episodes=n_total - n_before,
        discarded=sum(discarded_now.values()),
        discard_reasons=dict(discarded_now),
        seconds=time.perf_counter() - started,
        interrupted=interrupted is not None,
        video_backend=backend,
    )
    _log_summary(summary, cfg)
    if interrupted is not None:
        raise interrupted
    if cfg.push_to_hub:
        summary.pushed_url = push_dataset(cfg.repo_id, root, private=cfg.private)
    return summary


def _log_summary(s: RecordSummary, cfg: RecordConfig) -> None:
    reasons = ", ".join(f"{n} {r}" for r, n in sorted(s.discard_reasons.items())) or "none"
    logger.info(
        "%s: %d episodes, %d frames at %s (%d added this run in %.1f s; %d attempts discarded: %s).",
        s.repo_id,
        s.num_episodes,
        s.num_frames,
        s.root,
        s.added_episodes,
        s.seconds,
        s.discarded,
        reasons,
    )
    if s.interrupted:
        logger.warning(
            "Interrupted: the %d finished episodes are kept. Continue with: %s --resume=true",
            s.num_episodes,
            cfg.command(),
        )
        return
    logger.info(
        "Split: %d train, %d val (the last %d). Train on the train episodes with: lerobot-train "
        "--dataset.repo_id=%s --dataset.root=%s --dataset.eval_split=%s ... (or --dataset.episodes=[...] "
        "with lerobot_suture.datasets.train_episodes(root)).",
        len(s.train_episodes),
        len(s.val_episodes),
        len(s.val_episodes),
        s.repo_id,
        s.root,
        cfg.val_fraction,
    )
