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
    lerobot-suture record --config_path=datasets/suture_expert.yaml --repo_id=$HF_USER/suture_expert
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import shlex
import shutil
import signal
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import gymnasium as gym
import numpy as np

from lerobot_suture.datasets import metadata
from lerobot_suture.datasets.split import info_splits, split_episodes
from lerobot_suture.datasets.video import resolve_video_backend
from lerobot_suture.expert import ExpertConfig, ScriptedExpert
from lerobot_suture.registration import ENV_ID, MAX_EPISODE_STEPS
from lerobot_suture.rollout_expert import iter_expert_steps
from lerobot_suture.sim import suture_env, task
from lerobot_suture.sim.scenarios import SCENARIOS

logger = logging.getLogger(__name__)

COMMAND = "lerobot-suture record"
TASK = task.TASK
"""The task string of every frame (LeRobot's ``task``)."""
ROBOT_TYPE = "psm"
FPS = round(1.0 / task.CONTROL_DT)
"""Dataset fps: the env's control rate (10 Hz)."""
MAX_STEPS_AFTER_SUCCESS = 10
"""Most control steps ``--steps_after_success`` records past success: 6 mm more of the 31 mm needle
through the tissue (the expert's nominal insertions of seeds 0-39 all stay successful through 10; an
episode whose success lapses is discarded)."""

IMAGE_KEY = "observation.images.endoscope"
STATE_KEY = "observation.state"
ENV_STATE_KEY = "observation.environment_state"
NEEDLE_KEYPOINTS_KEY = "observation.needle_keypoints"
ACTION_KEY = "action"
REWARD_KEY = "next.reward"
SUCCESS_KEY = "next.success"
DONE_KEY = "next.done"

POSE_NAMES = ["x", "y", "z", "r11", "r21", "r31", "r12", "r22", "r32", "jaw"]
"""Jaw-tip pose: position (m), first two columns of the rotation matrix, jaw closure (1 = closed)."""
ENV_STATE_NAMES = (
    [f"entry_{a}" for a in "xyz"]
    + [f"exit_{a}" for a in "xyz"]
    + [f"needle_centre_{a}" for a in "xyz"]
    + ["needle_r11", "needle_r21", "needle_r31", "needle_r12", "needle_r22", "needle_r32"]
    + [f"needle_tip_{a}" for a in "xyz"]
)
NEEDLE_KEYPOINT_NAMES = [f"{point}_{axis}" for point in ("tip", "middle", "tail") for axis in "xy"]
"""The needle in the endoscope image: normalized x (right) and y (down) of its tip, middle and tail."""

_MAX_DISCARD_RATIO = 1.0
"""A run stops when the attempts it discards exceed this fraction of --num_episodes (and 10)."""


# ---------------------------------------------------------------------------------------------- config
def validate_repo_id(repo_id: str) -> None:
    """Check ``repo_id`` is ``USER/NAME`` as the Hugging Face Hub accepts it; no network.

    Raises:
        ValueError: naming what is wrong and the form expected.
    """
    if not repo_id:
        raise ValueError(
            "`repo_id` is required: pass --repo_id=USER/NAME (your Hugging Face user or organisation and "
            "a dataset name, e.g. --repo_id=alice/suture_expert)."
        )
    parts = repo_id.split("/")
    if len(parts) != 2 or not all(parts):
        raise ValueError(
            f"`repo_id` must be USER/NAME with exactly one '/', e.g. alice/suture_expert. Got {repo_id!r}."
        )
    from huggingface_hub.utils import HFValidationError
    from huggingface_hub.utils import validate_repo_id as hf_validate

    try:
        hf_validate(repo_id)
    except HFValidationError as exc:
        raise ValueError(
            f"`repo_id` {repo_id!r} is not a valid Hugging Face repo id: use letters, digits, '-', '_' "
            f"and '.', at most 96 characters, no '--' or '..'. ({exc})"
        ) from exc


@dataclass
class RecordConfig:
    """Flags of ``lerobot-suture record`` (draccus: ``--field=value``, or ``--config_path=FILE.yaml``).

    Args:
        repo_id: ``USER/NAME`` of the dataset on the Hugging Face Hub (also its local name).
        root: directory the dataset is written to; None: ``$HF_LEROBOT_HOME/<repo_id>`` (LeRobot's home,
            ``~/.cache/huggingface/lerobot``). It must not exist unless ``resume`` is true.
        num_episodes: successful episodes the dataset holds when done (the paper: 100 train + 33 val).
        val_fraction: fraction of episodes held out for validation, in [0, 1): the last
            ``ceil(num_episodes * val_fraction)`` episodes, LeRobot's ``--dataset.eval_split`` rule. It must
            leave a training episode (0 for a single episode).
        obs_type: ``pixels_agent_pos`` (endoscope + state, the paper's), ``pixels_agent_pos_state`` (adds
            the privileged 18-dim ``observation.environment_state``) or ``state`` (no image).
        image_size: endoscope image side (px), in [16, 640].
        scenario: perturbation scenario (``lerobot_suture.sim.scenarios.SCENARIOS``); the expert fails
            under some of them and those episodes are discarded.
        seed: env seed of the first attempt; attempt ``k`` uses ``seed + k``.
        grasp: the grasp's randomization (``task.GRASP_RANGES``): ``narrow``, that of every scene a
            policy is tested in, or ``wide``, which contains it and makes the needle's pose in the jaw
            change the expert's action enough that a policy must read it from the image.
        grasp_blind_expert: the expert plans with the nominal grasp instead of the true one, as a policy
            that does not read the needle must (``ExpertConfig.assume_nominal_grasp``). Its motion then
            does not depend on the grasp, so where the needle is in the image cannot be told from the
            jaw and the phantom: only from the needle (the target of ``needle_keypoints_weight``).
        steps_after_success: control steps recorded after the insertion succeeds, the expert driving on
            (its planned protrusion raised by the arc it turns in them, :func:`expert_config`). A policy's
            episode ends when the throw is over, so the action chunks it predicts there then reach into
            demonstrated motion instead of the padded stop at a demonstration's last frame. 0: episodes
            end at success (the paper's demonstrations).
        video: store images as MP4 video (true) or as PNG frames in the parquet files (false).
        checkpoint_every: episodes between durable checkpoints (finalize + resume): a SIGKILL loses
            at most this many; each checkpoint starts new data/video files. >= 1.
        resume: continue the dataset at ``root`` up to ``num_episodes`` (after rolling back any
            episodes a killed run left unfinished).
        push_to_hub: push the dataset to ``repo_id`` when done (needs a token: `hf auth login`). The
            token and the Hub are checked before recording starts.
        private: create the Hub repository as private (true) or public (false).
    """

    # Dataset.
    repo_id: str = ""  # USER/NAME on the Hugging Face Hub (required)
    root: str | None = None  # dataset directory (default: $HF_LEROBOT_HOME/<repo_id>)
    num_episodes: int = 133  # successful episodes in the finished dataset
    val_fraction: float = 0.25  # held-out validation fraction: the last ceil(n * f) episodes
    # Environment.
    obs_type: str = "pixels_agent_pos"  # pixels_agent_pos | pixels_agent_pos_state | state
    image_size: int = 96  # endoscope image side (px)
    scenario: str = "nominal"  # perturbation scenario the expert is recorded in
    grasp: str = "narrow"  # grasp randomization: narrow (the test scenes) | wide
    grasp_blind_expert: bool = False  # the expert plans with the nominal grasp, not the true one
    seed: int = 0  # env seed of the first attempt; attempt k uses seed + k
    steps_after_success: int = 0  # control steps recorded past success, the expert driving on
    # Storage.
    video: bool = True  # images as MP4 video (true) or PNG frames (false)
    checkpoint_every: int = 10  # episodes between durable checkpoints (what a SIGKILL can lose)
    # Resume and publish.
    resume: bool = False  # continue the dataset at --root up to --num_episodes
    push_to_hub: bool = False  # push to the Hub when done (token checked first)
    private: bool = False  # create the Hub repository as private

    def __post_init__(self):
        validate_repo_id(self.repo_id)
        if self.num_episodes < 1:
            raise ValueError(f"`num_episodes` must be >= 1. Got {self.num_episodes}.")
        if not (0.0 <= self.val_fraction < 1.0):
            raise ValueError(f"`val_fraction` must be in [0, 1). Got {self.val_fraction}.")
        split_episodes(self.num_episodes, self.val_fraction)  # the finished dataset has a training episode
        if self.obs_type not in suture_env.OBS_TYPES:
            raise ValueError(f"`obs_type` must be one of {suture_env.OBS_TYPES}. Got {self.obs_type!r}.")
        if not 16 <= self.image_size <= 640:
            raise ValueError(f"`image_size` must be in [16, 640] px. Got {self.image_size}.")
        if self.scenario not in SCENARIOS:
            raise ValueError(f"`scenario` must be one of {SCENARIOS}. Got {self.scenario!r}.")
        if self.grasp not in task.GRASP_RANGES:
            raise ValueError(f"`grasp` must be one of {list(task.GRASP_RANGES)}. Got {self.grasp!r}.")
        if not 0 <= self.seed < 2**32 - 1_000_000:
            raise ValueError(f"`seed` must be in [0, 2**32 - 1e6). Got {self.seed}.")
        if self.checkpoint_every < 1:
            raise ValueError(f"`checkpoint_every` must be >= 1. Got {self.checkpoint_every}.")
        if not 0 <= self.steps_after_success <= MAX_STEPS_AFTER_SUCCESS:
            raise ValueError(
                f"`steps_after_success` must be in [0, {MAX_STEPS_AFTER_SUCCESS}] control steps (the needle "
                f"is a semicircle; driving on further pushes the jaw into the tissue). Got "
                f"{self.steps_after_success}."
            )

    @property
    def has_images(self) -> bool:
        return "pixels" in self.obs_type

    def dataset_root(self) -> Path:
        """``root``, or LeRobot's default ``$HF_LEROBOT_HOME/<repo_id>``."""
        if self.root is not None:
            return Path(self.root).expanduser()
        from lerobot.utils.constants import HF_LEROBOT_HOME

        return Path(HF_LEROBOT_HOME) / self.repo_id

    def command(self) -> str:
        """The command that records this dataset from scratch (every flag spelled out)."""
        flags = [f"--repo_id={self.repo_id}"]
        if self.root is not None:
            flags.append(f"--root={self.root}")
        for name in ("num_episodes", "val_fraction", "obs_type", "image_size", "scenario", "seed", "video"):
            value = getattr(self, name)
            flags.append(f"--{name}={str(value).lower() if isinstance(value, bool) else value}")
        if self.grasp != "narrow":
            flags.append(f"--grasp={self.grasp}")
        if self.grasp_blind_expert:
            flags.append("--grasp_blind_expert=true")
        if self.steps_after_success:
            flags.append(f"--steps_after_success={self.steps_after_success}")
        if self.checkpoint_every != 10:
            flags.append(f"--checkpoint_every={self.checkpoint_every}")
        return " ".join([COMMAND, *(shlex.quote(f) for f in flags)])


def expert_config(steps_after_success: int, grasp_blind_expert: bool = False) -> ExpertConfig:
    """The recording expert: the default one, driving on through ``steps_after_success`` control steps
    past its usual protrusion (at ``drive_rate``), so it still turns the needle in them; with
    ``grasp_blind_expert`` it plans with the nominal grasp instead of the true one."""
    default = ExpertConfig()
    extra = steps_after_success * default.drive_rate * task.CONTROL_DT  # rad of arc
    return dataclasses.replace(
        default,
        protrusion_angle=default.protrusion_angle + extra,
        assume_nominal_grasp=grasp_blind_expert,
    )


def parse_config(argv: list[str] | None = None) -> RecordConfig:
    """Parse ``lerobot-suture record`` flags as LeRobot's scripts do (draccus, ``--config_path`` files)."""
    import draccus

    return draccus.parse(config_class=RecordConfig, args=argv, prog=COMMAND, exit_on_error=False)


def dataset_features(obs_type: str, image_size: int, video: bool) -> dict[str, dict]:
    """LeRobot feature specification of the dataset (``LeRobotDataset.create(features=...)``)."""
    features: dict[str, dict] = {}
    if "pixels" in obs_type:
        features[IMAGE_KEY] = {
            "dtype": "video" if video else "image",
            "shape": (image_size, image_size, 3),
            "names": ["height", "width", "channels"],
        }
        features[NEEDLE_KEYPOINTS_KEY] = {
            "dtype": "float32",
            "shape": (len(NEEDLE_KEYPOINT_NAMES),),
            "names": NEEDLE_KEYPOINT_NAMES,
        }
    features[STATE_KEY] = {"dtype": "float32", "shape": (10,), "names": list(POSE_NAMES)}
    if obs_type in ("state", "pixels_agent_pos_state"):
        features[ENV_STATE_KEY] = {"dtype": "float32", "shape": (18,), "names": list(ENV_STATE_NAMES)}
    features[ACTION_KEY] = {"dtype": "float32", "shape": (10,), "names": list(POSE_NAMES)}
    features[REWARD_KEY] = {"dtype": "float32", "shape": (1,), "names": None}
    features[SUCCESS_KEY] = {"dtype": "bool", "shape": (1,), "names": None}
    features[DONE_KEY] = {"dtype": "bool", "shape": (1,), "names": None}
    return features


# --------------------------------------------------------------------------------------------- rollout
@dataclass
class ExpertRollout:
    """One expert episode as dataset frames, with its outcome."""

    seed: int
    frames: list[dict]
    success: bool
    info: dict
    reason: str | None = None
    """Why the episode failed (a short category), None on success."""
    detail: str | None = None

    @property
    def length(self) -> int:
        return len(self.frames)


def _failure_reason(info: dict, steps: int) -> tuple[str, str]:
    """(category, detail) of a failed insertion, from the env's final ``info``."""
    entry, exit_ = info["entry_error_m"], info["exit_error_m"]
    if not info["needle_grasped"]:
        return "needle dropped", f"the jaw lost the needle; episode ended after {steps} steps"
    if not math.isfinite(entry):
        return "needle never entered the tissue", f"no entry within {steps} steps"
    if entry > task.ENTRY_TOLERANCE:
        return (
            "entry error above tolerance",
            f"entry error {entry * 1e3:.2f} mm > {task.ENTRY_TOLERANCE * 1e3} mm",
        )
    if not math.isfinite(exit_):
        return "needle did not emerge", f"no exit within {steps} steps"
    if exit_ > task.EXIT_TOLERANCE:
        return (
            "exit error above tolerance",
            f"exit error {exit_ * 1e3:.2f} mm > {task.EXIT_TOLERANCE * 1e3} mm",
        )
    return "time limit", f"not done within {steps} steps (protrusion {info['protrusion_m'] * 1e3:.2f} mm)"


def make_env(obs_type: str, image_size: int, scenario: str, grasp: str = "narrow"):
    """The env the dataset is recorded in (``gym.make`` of :data:`~lerobot_suture.ENV_ID`)."""
    return gym.make(
        ENV_ID,
        obs_type=obs_type,
        image_size=image_size,
        scenario=scenario,
        grasp=grasp,
        disable_env_checker=True,
    )


def rollout_expert(
    env,
    expert,
    seed: int,
    on_step: Callable[[], None] | None = None,
    steps_after_success: int = 0,
) -> ExpertRollout:
    """Run the expert for one episode from ``env.reset(seed=seed)``; frames in dataset layout.

    Args:
        env: the (wrapped) env from :func:`make_env`.
        expert: a :class:`~lerobot_suture.expert.ScriptedExpert`.
        seed: env seed.
        on_step: called after every control step (progress).
        steps_after_success: control steps recorded after the insertion succeeds; the episode counts as a
            success only if all of them are recorded and the insertion holds through every one.
    """
    obs, info = env.reset(seed=seed)
    frames = []
    # The needle's place in the image is recorded with the image (a target for the image encoders).
    keypoints = "pixels" in obs
    for step in iter_expert_steps(env, expert, obs, steps_after_success, needle_keypoints=keypoints):
        frame = {
            STATE_KEY: step.obs["agent_pos"],
            ACTION_KEY: np.asarray(step.action, dtype=np.float32),
            REWARD_KEY: np.array([step.reward], dtype=np.float32),
            SUCCESS_KEY: np.array([bool(step.info["is_success"])]),
            DONE_KEY: np.array([step.done]),
            "task": TASK,
        }
        if "pixels" in step.obs:
            frame[IMAGE_KEY] = step.obs["pixels"]["endoscope"]
            frame[NEEDLE_KEYPOINTS_KEY] = step.needle_keypoints
        if "environment_state" in step.obs:
            frame[ENV_STATE_KEY] = step.obs["environment_state"]
        frames.append(frame)
        info = step.info
        if on_step is not None:
            on_step()
    rollout = ExpertRollout(seed=seed, frames=frames, success=False, info=info)
    succeeded = [bool(f[SUCCESS_KEY][0]) for f in frames]
    if True not in succeeded:
        rollout.reason, rollout.detail = _failure_reason(info, len(frames))
        return rollout
    first = succeeded.index(True)
    after = len(frames) - 1 - first
    if not all(succeeded[first:]):
        lost = first + succeeded[first:].index(False)
        rollout.reason = "success lost while driving on"
        rollout.detail = (
            f"succeeded at step {first + 1}, lost it at step {lost + 1} of the {steps_after_success} steps "
            "after success; record with a smaller --steps_after_success"
        )
    elif after < steps_after_success:
        rollout.reason = "time limit after success"
        rollout.detail = f"{after} of the {steps_after_success} steps after success fit in the time limit"
    else:
        rollout.success = True
    return rollout


def regenerate_episode(root: str | Path, episode_index: int) -> dict[str, np.ndarray]:
    """Re-run the expert with the seed of episode ``episode_index`` of the dataset at ``root``.

    Returns:
        The episode's non-video features stacked over frames (``{key: (T, ...)}``), images included
        (uncompressed, as rendered) when the dataset has them.

    Raises:
        RuntimeError: if the episode does not reproduce (a different length or no success).
    """
    log = metadata.read_episode_log(root)
    entry = log["episodes"][episode_index]
    env = make_env(**log["env_kwargs"])
    try:
        rollout = rollout_expert(
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


# --------------------------------------------------------------------------------------------- signals
class RecordingInterrupted(KeyboardInterrupt):
    """Ctrl-C or ``kill`` (SIGINT / SIGTERM) stopped a recording; finished episodes were kept."""

    def __init__(self, signum: int):
        super().__init__(f"recording stopped by {signal.Signals(signum).name}")
        self.signum = signum


class _StopSignals:
    """Turns SIGINT/SIGTERM into :class:`RecordingInterrupted`, held back while a critical section runs.

    Saving an episode (add_frame ... save_episode ... checkpoint) must not be cut in half; a signal
    that arrives during it is raised as soon as it ends. Once ``stopping`` is set (cleanup), further
    signals are only logged.
    """

    _SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self._previous: dict[int, object] = {}
        self._depth = 0
        self._pending: int | None = None
        self.stopping = False

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for sig in self._SIGNALS:
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc):
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()
        return False

    def _handle(self, signum, frame):
        if self.stopping:
            logger.warning(
                "%s received: already stopping, finishing the dataset.", signal.Signals(signum).name
            )
            return
        if self._depth > 0:
            self._pending = signum
            return
        raise RecordingInterrupted(signum)

    @contextlib.contextmanager
    def deferred(self):
        self._depth += 1
        try:
            yield
        finally:
            self._depth -= 1
        if self._depth == 0 and self._pending is not None and not self.stopping:
            signum, self._pending = self._pending, None
            raise RecordingInterrupted(signum)


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


def _versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for dist in ("lerobot_suture", "lerobot", "mujoco", "gymnasium"):
        try:
            out[dist] = version(dist)
        except PackageNotFoundError:
            out[dist] = "unknown"
    return out


def _new_log(cfg: RecordConfig) -> dict:
    return {
        "format_version": metadata.FORMAT_VERSION,
        "repo_id": cfg.repo_id,
        "task": TASK,
        "fps": FPS,
        "gym_id": ENV_ID,
        "max_episode_steps": MAX_EPISODE_STEPS,
        "env_kwargs": {
            "obs_type": cfg.obs_type,
            "image_size": cfg.image_size,
            "scenario": cfg.scenario,
            "grasp": cfg.grasp,
        },
        "expert": {
            "class": "lerobot_suture.expert.ScriptedExpert",
            "config": dataclasses.asdict(expert_config(cfg.steps_after_success, cfg.grasp_blind_expert)),
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


_RESUME_FIELDS = ("obs_type", "image_size", "scenario", "grasp")


def _check_resumable(cfg: RecordConfig, log: dict, root: Path) -> None:
    recorded = {
        "grasp": "narrow",  # absent in logs before it existed
        **log["env_kwargs"],
        "video": log["video"],
        "seed": log["seed"],
        "steps_after_success": log.get("steps_after_success", 0),  # absent in logs before it existed
        "grasp_blind_expert": log["expert"]["config"].get("assume_nominal_grasp", False),
    }
    for name in (*_RESUME_FIELDS, "video", "seed", "steps_after_success", "grasp_blind_expert"):
        if getattr(cfg, name) != recorded[name]:
            value = str(recorded[name]).lower() if isinstance(recorded[name], bool) else recorded[name]
            raise ValueError(
                f"`{name}` differs from the dataset at {root}: it was recorded with --{name}={value}, got "
                f"--{name}={getattr(cfg, name)}. Resume with --{name}={value}, or record a new dataset "
                "with another --root."
            )
    if log["repo_id"] != cfg.repo_id:
        logger.warning("Dataset at %s was recorded as %s; it is now %s.", root, log["repo_id"], cfg.repo_id)
        log["repo_id"] = cfg.repo_id


def _prepare_root(cfg: RecordConfig, root: Path) -> tuple[dict, bool]:
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
        return _new_log(cfg), True
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
        return _new_log(cfg), True
    return log, False


def _finish(dataset, root: Path, log: dict, cfg: RecordConfig) -> None:
    """Finalize; write split, episode log, card; mark the dataset clean."""
    from lerobot.datasets.io_utils import write_info

    from lerobot_suture.datasets.card import write_dataset_card

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
    log, fresh = _prepare_root(cfg, root)
    if cfg.push_to_hub:
        from lerobot_suture.datasets.hub import check_hub_access

        check_hub_access(cfg.repo_id)  # fail fast, before any recording

    import datasets as hf_datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from tqdm import tqdm

    os.environ.setdefault("SVT_LOG", "1")  # the AV1 encoder's banner, per episode, otherwise
    backend = resolve_video_backend() if cfg.video and cfg.has_images else None
    features = dataset_features(cfg.obs_type, cfg.image_size, cfg.video)
    expert = ScriptedExpert(ExpertConfig(**log["expert"]["config"]))
    env = make_env(cfg.obs_type, cfg.image_size, cfg.scenario, cfg.grasp)
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
    stops = _StopSignals()
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
                result = rollout_expert(
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
        from lerobot_suture.datasets.hub import push_dataset

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


def main(argv: list[str] | None = None) -> None:
    """``lerobot-suture record``: parse flags (draccus) and record. Exits non-zero on failure.

    Exit status: 0 done; 2 bad flags or root; 1 other failures; 128 + signal number when interrupted
    (130 for Ctrl-C), with every finished episode kept.
    """
    import argparse

    import draccus

    from lerobot_suture.cli import flag_error
    from lerobot_suture.datasets.hub import HubPushError

    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("lerobot.configs.video").setLevel(logging.WARNING)  # "Using video codec" per file
    with contextlib.suppress(ImportError):  # FFmpeg's own INFO lines ("Starting second pass ...")
        import av.logging

        av.logging.set_level(av.logging.ERROR)
    try:
        cfg = parse_config(argv)
    except (draccus.utils.DraccusException, argparse.ArgumentError) as exc:
        print(f"{COMMAND}: error: {flag_error(exc)} (`{COMMAND} --help` lists the flags)", file=sys.stderr)
        raise SystemExit(2) from None
    try:
        record(cfg)
    except RecordingInterrupted as exc:
        raise SystemExit(128 + exc.signum) from None
    except KeyboardInterrupt:
        raise SystemExit(130) from None
    except (FileExistsError, FileNotFoundError, ValueError) as exc:
        print(f"{COMMAND}: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    except HubPushError as exc:
        print(f"{COMMAND}: error: {exc}", file=sys.stderr)
        raise SystemExit(1) from None


if __name__ == "__main__":
    main()
