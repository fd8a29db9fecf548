"""Flags of ``lerobot-suture record``: :class:`RecordConfig` (validated at construction), the recording
expert they describe, and their parsing as LeRobot's scripts parse theirs (draccus)."""

from __future__ import annotations

import dataclasses
import shlex
from dataclasses import dataclass, field
from pathlib import Path

from lerobot_suture.datasets.hub import validate_repo_id
from lerobot_suture.datasets.split import split_episodes
from lerobot_suture.expert import ExpertConfig
from lerobot_suture.sim import suture_env, task
from lerobot_suture.sim.appearance import AppearanceConfig
from lerobot_suture.sim.regrasp_target import check_regrasp_source
from lerobot_suture.sim.scenarios import SCENARIOS
from lerobot_suture.sim.state_layout import STATE_PARTS
from lerobot_suture.sim.tasks import check_scenario

COMMAND = "lerobot-suture record"
MAX_STEPS_AFTER_SUCCESS = 10
"""Most control steps ``--steps_after_success`` records past success: 6 mm more of the 31 mm needle
through the tissue (the expert's nominal insertions of seeds 0-39 all stay successful through 10; an
episode whose success lapses is discarded)."""


@dataclass
class RecordConfig:
    """Flags of ``lerobot-suture record`` (draccus: ``--field=value``, or ``--config_path=FILE.yaml``).

    Args:
        repo_id: ``USER/NAME`` of the dataset on the Hugging Face Hub (also its local name).
        root: directory the dataset is written to; None: ``$HF_LEROBOT_HOME/<repo_id>`` (LeRobot's home,
            ``~/.cache/huggingface/lerobot``). It must not exist unless ``resume`` is true.
        num_episodes: successful episodes the dataset holds when done (the paper: 100 train + 33 val).
        task: the task of the family (``lerobot_suture.sim.tasks.TASKS``) the expert performs:
            ``insertion`` (the paper's), ``pickup``, ``extraction`` or ``running_suture``.
        val_fraction: fraction of episodes held out for validation, in [0, 1): the last
            ``ceil(num_episodes * val_fraction)`` episodes, LeRobot's ``--dataset.eval_split`` rule. It must
            leave a training episode (0 for a single episode).
        obs_type: ``pixels_agent_pos`` (endoscope + state, the paper's), ``pixels_agent_pos_state`` (adds
            the privileged 18-dim ``observation.environment_state``) or ``state`` (no image).
        image_size: endoscope image side (px), in [16, 640].
        wrist_camera: also record the image of a camera on the instrument's shaft
            (``observation.images.wrist``, ``image_size`` too); needs an ``obs_type`` with pixels.
        marks: also record the current throw's entry and exit marks, as a registered wound gives them
            (``observation.environment_state``, (6,) m); needs ``obs_type=pixels_agent_pos``.
        subtask: also record the high level's subtask and throw (``lerobot_suture.sim.subtasks``: one-hot and
            throw, (5,), after the marks in ``observation.environment_state``); needs ``obs_type=pixels_agent_pos``.
        regrasp_target: also record the regrasp planned through the marks, in the jaw frame
            (``lerobot_suture.sim.regrasp_target``: (9,), after the marks and the subtask in
            ``observation.environment_state``); needs ``obs_type=pixels_agent_pos``. With
            ``--regrasp_aim=marks`` the expert's regrasps go where it says.
        regrasp_from: where that plan comes from: ``marks`` (the arc through them) or ``release`` (the needle where
            the jaw let go of it; record it with ``--regrasp_aim=release``).
        relative_actions: record each action as the motion from the jaw's measured pose, in the jaw frame
            (``lerobot_suture.sim.relative_actions``): an ``ensemble_diffusion`` policy trained on it composes
            its actions with the measured pose in its post-processor, and runs on the plain env.
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
        approach_detour: m, [0, 0.03]; > 0: the expert approaches via a waypoint this far to one side of
            the entry-exit line, the side drawn per episode (``ExpertConfig.approach_detour``): a dataset
            of two equally valid strategies, for testing whether a detector mistakes them for uncertainty.
        regrasp_miss: m, 0 or [0.0006, 0.003], extraction and running suture only; > 0: the first regrasp of
            each extraction aims this far beside the lodged needle and misses, and the expert reaches again
            (``ExpertConfig.regrasp_miss``): demonstrations of recovering a missed regrasp, which the expert
            never needs otherwise.
        regrasp_noise: m, [0, 0.002], extraction and running suture only; > 0: while the expert reaches for
            a regrasp, the env executes its jaw position plus Gaussian noise of this deviation per axis and
            step, and the dataset keeps the expert's own action (DART, ``ExpertConfig.regrasp_noise``):
            demonstrations that correct a reach gone off, and recover a closing beside the needle.
        regrasp_aim: ``needle`` or ``marks``, extraction and running suture only: what the expert's regrasps
            aim at, the needle's true pose or the grasp planned through the registered marks
            (``ExpertConfig.regrasp_aim``).
        regrasp_settle: control steps, [0, 10], extraction and running suture only; > 0: the expert holds the
            open jaw on each regrasp's pose that long before it closes (``ExpertConfig.regrasp_settle``), so the
            closing is demonstrated where the jaw stands still.
        regrasp_reach_offset: m, [0, 0.003], extraction and running suture only; > 0: each regrasp's reach ends
            up to this far beside the point short of the grasp, and the advance onto the grasp corrects it
            (``ExpertConfig.regrasp_reach_offset``): demonstrations of the correction a policy's reach needs.
        steps_after_success: control steps recorded after the insertion succeeds, the expert driving on
            (its planned protrusion raised by the arc it turns in them, :func:`expert_config`). A policy's
            episode ends when the throw is over, so the action chunks it predicts there then reach into
            demonstrated motion instead of the padded stop at a demonstration's last frame. 0: episodes
            end at success (the paper's demonstrations).
        appearance: per-episode appearance randomization of the endoscope's view (light, tissue and
            instrument colour, tissue texture, haze, blur, noise, endoscope pose jitter), every option
            off by default: ``--appearance.light_intensity=0.3`` etc. (ranges and units in
            ``lerobot_suture.sim.appearance``). It changes no trajectory: an episode's seed gives the
            same motion with and without it. Logged in ``meta/suture_episodes.json`` and listed in the
            dataset card.
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
    task: str = "insertion"  # the task recorded: insertion | pickup | extraction | running_suture
    obs_type: str = "pixels_agent_pos"  # pixels_agent_pos | pixels_agent_pos_state | state
    image_size: int = 96  # endoscope image side (px)
    wrist_camera: bool = False  # also record the wrist camera (observation.images.wrist, image_size too)
    marks: bool = False  # also record the wound's marks (observation.environment_state, (6,) m)
    subtask: bool = False  # also record the high level's subtask and throw (observation.environment_state)
    regrasp_target: bool = False  # also record the planned regrasp, in the jaw frame (environment_state)
    regrasp_from: str = "marks"  # the planned regrasp's source: marks | release (where the jaw let go)
    relative_actions: bool = False  # actions as the motion from the jaw's measured pose, in the jaw frame
    scenario: str = "nominal"  # perturbation scenario the expert is recorded in
    grasp: str = "narrow"  # grasp randomization: narrow (the test scenes) | wide
    grasp_blind_expert: bool = False  # the expert plans with the nominal grasp, not the true one
    approach_detour: float = 0.0  # m; > 0: the expert approaches via either side, drawn per episode
    regrasp_miss: float = 0.0  # m; > 0: each extraction's first regrasp misses by this much, then recovers
    regrasp_noise: float = 0.0  # m; > 0: noise executed, not recorded, while the expert reaches to regrasp
    regrasp_aim: str = "needle"  # what the expert's regrasps aim at: needle (its pose) | marks | release
    regrasp_settle: int = 0  # control steps the open jaw holds a regrasp's pose before it closes
    regrasp_reach_offset: float = 0.0  # m; > 0: each regrasp's reach ends off line, the advance corrects it
    seed: int = 0  # env seed of the first attempt; attempt k uses seed + k
    steps_after_success: int = 0  # control steps recorded past success, the expert driving on
    appearance: AppearanceConfig = field(default_factory=AppearanceConfig)  # endoscope view randomization
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
        if self.wrist_camera and not self.has_images:
            raise ValueError(
                f"`wrist_camera` records an image; `obs_type`={self.obs_type!r} has none. Pass "
                "--obs_type=pixels_agent_pos."
            )
        for name in STATE_PARTS:
            if getattr(self, name) and self.obs_type != "pixels_agent_pos":
                raise ValueError(
                    f"`{name}` records into observation.environment_state; `obs_type`={self.obs_type!r} "
                    "holds the privileged state there. Pass --obs_type=pixels_agent_pos."
                )
        if self.scenario not in SCENARIOS:
            raise ValueError(f"`scenario` must be one of {SCENARIOS}. Got {self.scenario!r}.")
        check_scenario(self.task, self.scenario)  # also names the tasks when `task` is none of them
        if self.grasp not in task.GRASP_RANGES:
            raise ValueError(f"`grasp` must be one of {list(task.GRASP_RANGES)}. Got {self.grasp!r}.")
        if not 0 <= self.seed < 2**32 - 1_000_000:
            raise ValueError(f"`seed` must be in [0, 2**32 - 1e6). Got {self.seed}.")
        for name in (
            "approach_detour",
            "regrasp_miss",
            "regrasp_noise",
            "regrasp_aim",
            "regrasp_settle",
            "regrasp_reach_offset",
        ):
            if getattr(self, name) not in (0, "needle"):
                ExpertConfig(**{name: getattr(self, name)})  # its range, named as the expert's
                if name != "approach_detour" and self.task not in ("extraction", "running_suture"):
                    raise ValueError(
                        f"`{name}` shapes an extraction's regrasp; task {self.task!r} has none. Use it with "
                        "--task=extraction or --task=running_suture."
                    )
        check_regrasp_source(self.regrasp_from, self.regrasp_target, "--regrasp_target=true")
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
        if self.task != "insertion":
            flags.append(f"--task={self.task}")
        for name in ("num_episodes", "val_fraction", "obs_type", "image_size", "scenario", "seed", "video"):
            value = getattr(self, name)
            flags.append(f"--{name}={str(value).lower() if isinstance(value, bool) else value}")
        if self.grasp != "narrow":
            flags.append(f"--grasp={self.grasp}")
        if self.wrist_camera:
            flags.append("--wrist_camera=true")
        if self.marks:
            flags.append("--marks=true")
        if self.subtask:
            flags.append("--subtask=true")
        if self.regrasp_target:
            flags.append("--regrasp_target=true")
        if self.regrasp_from != "marks":
            flags.append(f"--regrasp_from={self.regrasp_from}")
        if self.relative_actions:
            flags.append("--relative_actions=true")
        if self.grasp_blind_expert:
            flags.append("--grasp_blind_expert=true")
        if self.approach_detour:
            flags.append(f"--approach_detour={self.approach_detour:g}")
        if self.regrasp_miss:
            flags.append(f"--regrasp_miss={self.regrasp_miss:g}")
        if self.regrasp_noise:
            flags.append(f"--regrasp_noise={self.regrasp_noise:g}")
        if self.regrasp_aim != "needle":
            flags.append(f"--regrasp_aim={self.regrasp_aim}")
        if self.regrasp_settle:
            flags.append(f"--regrasp_settle={self.regrasp_settle}")
        if self.regrasp_reach_offset:
            flags.append(f"--regrasp_reach_offset={self.regrasp_reach_offset:g}")
        if self.steps_after_success:
            flags.append(f"--steps_after_success={self.steps_after_success}")
        for name, value in self.appearance.active().items():
            flags.append(f"--appearance.{name}={value:g}")
        if self.checkpoint_every != 10:
            flags.append(f"--checkpoint_every={self.checkpoint_every}")
        return " ".join([COMMAND, *(shlex.quote(f) for f in flags)])


def expert_config(
    steps_after_success: int,
    grasp_blind_expert: bool = False,
    approach_detour: float = 0.0,
    regrasp_miss: float = 0.0,
    regrasp_noise: float = 0.0,
    regrasp_aim: str = "needle",
    regrasp_settle: int = 0,
    regrasp_reach_offset: float = 0.0,
) -> ExpertConfig:
    """The recording expert: the default one, driving on through ``steps_after_success`` control steps
    past its usual protrusion (at ``drive_rate``), so it still turns the needle in them; with
    ``grasp_blind_expert`` it plans with the nominal grasp instead of the true one; with
    ``approach_detour`` it approaches via either side of the entry-exit line (two strategies); with
    ``regrasp_miss`` each extraction's first regrasp misses and the expert recovers it; with ``regrasp_noise``
    the reach for a regrasp is executed with noise and recorded without (DART); ``regrasp_aim`` what the
    regrasps aim at; ``regrasp_settle`` how long the open jaw holds a regrasp's pose before it closes; with
    ``regrasp_reach_offset`` each reach ends beside the grasp's line and the advance corrects it."""
    default = ExpertConfig()
    extra = steps_after_success * default.drive_rate * task.CONTROL_DT  # rad of arc
    return dataclasses.replace(
        default,
        protrusion_angle=default.protrusion_angle + extra,
        assume_nominal_grasp=grasp_blind_expert,
        approach_detour=approach_detour,
        regrasp_miss=regrasp_miss,
        regrasp_noise=regrasp_noise,
        regrasp_aim=regrasp_aim,
        regrasp_settle=regrasp_settle,
        regrasp_reach_offset=regrasp_reach_offset,
    )


def parse_config(argv: list[str] | None = None) -> RecordConfig:
    """Parse ``lerobot-suture record`` flags as LeRobot's scripts do (draccus, ``--config_path`` files)."""
    import draccus

    return draccus.parse(config_class=RecordConfig, args=argv, prog=COMMAND, exit_on_error=False)
