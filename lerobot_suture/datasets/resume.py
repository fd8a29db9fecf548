"""Where a recording starts: a new episode log for an empty root, or, with ``--resume=true``, the dataset
a stopped run left there, rolled back to its last checkpoint and checked against the flags."""

from __future__ import annotations

import dataclasses
import logging
import shutil
from pathlib import Path

from lerobot_suture.datasets import metadata
from lerobot_suture.datasets.features import FPS
from lerobot_suture.datasets.record_config import COMMAND, RecordConfig, expert_config
from lerobot_suture.sim.appearance import AppearanceConfig
from lerobot_suture.sim.tasks import task_spec

# What a recording reports goes to one logger, the recorder's.
logger = logging.getLogger("lerobot_suture.datasets.record")


def _versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for dist in ("lerobot_suture", "lerobot", "mujoco", "gymnasium"):
        try:
            out[dist] = version(dist)
        except PackageNotFoundError:
            out[dist] = "unknown"
    return out


def new_episode_log(cfg: RecordConfig) -> dict:
    spec = task_spec(cfg.task)
    env_kwargs = {
        "obs_type": cfg.obs_type,
        "image_size": cfg.image_size,
        "scenario": cfg.scenario,
        "grasp": cfg.grasp,
    }
    if cfg.task != "insertion":
        env_kwargs["task"] = cfg.task  # absent for insertion: its logs read as before the task family
    if cfg.wrist_camera:
        env_kwargs["wrist_camera"] = True  # absent when off, as in the logs recorded before it existed
    if cfg.marks:
        env_kwargs["marks"] = True  # absent when off
    if cfg.subtask:
        env_kwargs["subtask"] = True  # absent when off
    if cfg.relative_actions:
        env_kwargs["relative_actions"] = True  # absent when off
    if cfg.regrasp_target:
        env_kwargs["regrasp_target"] = True  # absent when off
    if cfg.regrasp_from != "marks":
        env_kwargs["regrasp_from"] = cfg.regrasp_from  # absent for the plan through the marks
    if cfg.appearance.enabled:
        # Absent when off: the logs of datasets recorded without it read the same as before it existed.
        env_kwargs["appearance"] = dataclasses.asdict(cfg.appearance)
    return {
        "format_version": metadata.FORMAT_VERSION,
        "repo_id": cfg.repo_id,
        "task": spec.instruction,
        "fps": FPS,
        "gym_id": spec.gym_id,
        "max_episode_steps": spec.max_episode_steps,
        "env_kwargs": env_kwargs,
        "expert": {
            "class": "lerobot_suture.expert.ScriptedExpert",
            "config": dataclasses.asdict(
                expert_config(
                    cfg.steps_after_success,
                    cfg.grasp_blind_expert,
                    cfg.approach_detour,
                    cfg.regrasp_miss,
                    cfg.regrasp_noise,
                    cfg.regrasp_aim,
                    cfg.regrasp_settle,
                    cfg.regrasp_reach_offset,
                )
            ),
        },
        "steps_after_success": cfg.steps_after_success,
        "seed": cfg.seed,
        "next_seed": cfg.seed,
        "video": cfg.video,
        "val_fraction": cfg.val_fraction,
        "command": cfg.command(),
        "splits": {"train": [], "val": []},
        "episodes": [],
        "discarded": [],
        "runs": [],
        "versions": _versions(),
    }


_RESUME_FIELDS = (
    "task",
    "obs_type",
    "image_size",
    "scenario",
    "grasp",
    "wrist_camera",
    "marks",
    "subtask",
    "relative_actions",
    "regrasp_target",
    "regrasp_from",
)


def _check_resumable(cfg: RecordConfig, log: dict, root: Path) -> None:
    recorded = {
        "grasp": "narrow",  # absent in logs before it existed
        "task": "insertion",  # absent in insertion logs
        "wrist_camera": False,  # absent when off
        "marks": False,  # absent when off
        "subtask": False,  # absent when off
        "relative_actions": False,  # absent when off
        "regrasp_target": False,  # absent when off
        "regrasp_from": "marks",  # absent for the plan through the marks
        **{k: v for k, v in log["env_kwargs"].items() if k != "appearance"},
        "video": log["video"],
        "seed": log["seed"],
        "steps_after_success": log.get("steps_after_success", 0),  # absent in logs before it existed
        "grasp_blind_expert": log["expert"]["config"].get("assume_nominal_grasp", False),
        "approach_detour": log["expert"]["config"].get("approach_detour", 0.0),
        "regrasp_miss": log["expert"]["config"].get("regrasp_miss", 0.0),
        "regrasp_noise": log["expert"]["config"].get("regrasp_noise", 0.0),
        "regrasp_aim": log["expert"]["config"].get("regrasp_aim", "needle"),
    }
    for name in (
        *_RESUME_FIELDS,
        "video",
        "seed",
        "steps_after_success",
        "grasp_blind_expert",
        "approach_detour",
        "regrasp_miss",
        "regrasp_noise",
        "regrasp_aim",
    ):
        if getattr(cfg, name) != recorded[name]:
            value = str(recorded[name]).lower() if isinstance(recorded[name], bool) else recorded[name]
            raise ValueError(
                f"`{name}` differs from the dataset at {root}: it was recorded with --{name}={value}, got "
                f"--{name}={getattr(cfg, name)}. Resume with --{name}={value}, or record a new dataset "
                "with another --root."
            )
    recorded_appearance = AppearanceConfig.from_value(log["env_kwargs"].get("appearance"))
    if cfg.appearance != recorded_appearance:
        flags = " ".join(f"--appearance.{k}={v:g}" for k, v in recorded_appearance.active().items())
        raise ValueError(
            f"`appearance` differs from the dataset at {root}: it was recorded with "
            f"{flags or 'every appearance option off'}, got {cfg.appearance.active() or 'all off'}. Resume "
            "with the recorded options, or record a new dataset with another --root."
        )
    if log["repo_id"] != cfg.repo_id:
        logger.warning("Dataset at %s was recorded as %s; it is now %s.", root, log["repo_id"], cfg.repo_id)
        log["repo_id"] = cfg.repo_id


def prepare_root(cfg: RecordConfig, root: Path) -> tuple[dict, bool]:
    """Check ``root`` against ``--resume``; roll back a killed run. Returns (episode log, fresh)."""
    exists = root.exists() and (not root.is_dir() or any(root.iterdir()))
    if not cfg.resume:
        if exists:
            raise FileExistsError(
                f"The dataset root {root} already exists. Pass --resume=true to continue recording into it "
                f"(up to --num_episodes), or choose another --root (or delete {root})."
            )
        if root.exists():
            root.rmdir()  # an empty directory: LeRobot wants to create it
        return new_episode_log(cfg), True
    if not exists:
        raise FileNotFoundError(
            f"--resume=true but there is no dataset at {root} to resume. Pass the --root (and --repo_id) "
            "of the dataset to continue, or drop --resume to record a new one there."
        )
    checkpoint = metadata.read_checkpoint(root)
    if checkpoint is not None:
        if metadata.checkpoint_owner_alive(checkpoint):
            raise RuntimeError(
                f"Another recording (pid {checkpoint['pid']}) is writing to {root}. Wait for it to finish "
                "or stop it (Ctrl-C / kill keeps its finished episodes), then resume."
            )
        log = checkpoint["episode_log"]
        removed = metadata.roll_back_to_checkpoint(root, checkpoint)
        logger.warning(
            "The last recording into %s stopped without finishing (killed?): rolled back to its last "
            "checkpoint, %d episodes (%d unfinished files removed).",
            root,
            len(log["episodes"]),
            len(removed),
        )
    else:
        try:
            log = metadata.read_episode_log(root)
        except FileNotFoundError as exc:
            raise FileNotFoundError(
                f"Cannot resume {root}: it has no {metadata.EPISODE_LOG_PATH}, so it was not recorded by "
                f"`{COMMAND}`. Record a new dataset with another --root."
            ) from exc
        info = metadata.read_json(root / metadata.INFO_PATH)
        if info["total_episodes"] != len(log["episodes"]):
            raise RuntimeError(
                f"The dataset at {root} is inconsistent: meta/info.json counts {info['total_episodes']} "
                f"episodes, {metadata.EPISODE_LOG_PATH} {len(log['episodes'])}. It was changed outside "
                f"`{COMMAND}`; record a new dataset with another --root."
            )
    _check_resumable(cfg, log, root)
    if not log["episodes"]:
        shutil.rmtree(root)  # nothing kept: start afresh (the same seeds give the same episodes)
        return new_episode_log(cfg), True
    return log, False
