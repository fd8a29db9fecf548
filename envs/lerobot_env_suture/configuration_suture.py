"""``SutureEnvConfig``: the suturing env, its task family, as LeRobot's env type ``suture``."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_IMAGES, OBS_STATE

from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.sim.appearance import AppearanceConfig
from lerobot_suture.sim.regrasp_target import check_regrasp_source
from lerobot_suture.sim.scenarios import SCENARIOS
from lerobot_suture.sim.state_layout import PRIVILEGED_STATE_DIM, STATE_PARTS, state_size
from lerobot_suture.sim.suture_env import OBS_TYPES, check_image_side
from lerobot_suture.sim.tasks import DEFAULT_TASK, TASKS, check_scenario, task_spec

_TASK_BY_GYM_NAME = {spec.gym_id.split("/", 1)[1]: name for name, spec in TASKS.items()}

ENDOSCOPE_KEY = "pixels/endoscope"
WRIST_KEY = "pixels/wrist"


@EnvConfig.register_subclass("suture")
@dataclass
class SutureEnvConfig(EnvConfig):
    """MuJoCo suturing with a da Vinci-style arm (see ``lerobot_suture.sim.suture_env``).

    Args:
        task: which task of the family (``lerobot_suture.sim.tasks.TASKS``): ``insertion`` (the paper's),
            ``pickup``, ``extraction`` or ``running_suture``. Its gym id (``NeedleInsertion-v0``, ...) is accepted too.
        fps: control rate (Hz); fixed by the env at 10.
        episode_length: max control steps per episode; None: the task's own (``TaskSpec.max_episode_steps``).
        obs_type: ``pixels_agent_pos`` (endoscope + state, the paper's), ``state`` (state and
            privileged environment state, no image) or ``pixels_agent_pos_state`` (all three).
        image_size: endoscope image side (px).
        render_size: side (px) of the frames ``render()`` returns (eval videos).
        scenario: perturbation scenario, one of ``lerobot_suture.sim.scenarios.SCENARIOS``.
        scenario_onset_step: onset (control steps); None takes the scenario's default.
        scenario_magnitude: magnitude (rad or m); None takes the scenario's default.
        cbf: the control barrier function safety filter (``--env.cbf.enabled=true``).
        appearance: per-episode appearance randomization of the endoscope's view, every option off by
            default (``--env.appearance.light_intensity=0.3``; ranges in
            ``lerobot_suture.sim.appearance``).
        wrist_camera: add the image of a camera on the instrument's shaft (``observation.images.wrist``,
            ``image_size`` too); needs an ``obs_type`` with pixels.
        marks: add the current throw's entry and exit marks, as a registered wound gives them
            (``observation.environment_state``, (6,) m; ``lerobot_suture.sim.wound_marks``); needs
            ``obs_type=pixels_agent_pos``.
        subtask: add the high level's subtask and throw (``observation.environment_state``, (5,) after the
            marks; ``lerobot_suture.sim.subtasks``); needs ``obs_type=pixels_agent_pos``.
        regrasp_target: add the regrasp planned through the registered marks, in the jaw frame
            (``observation.environment_state``, (9,) after the marks and the subtask;
            ``lerobot_suture.sim.regrasp_target``); needs ``obs_type=pixels_agent_pos``.
        regrasp_from: where that plan comes from: ``marks`` (the arc through them) or ``release`` (the needle
            where the jaw let go of it at the end of the insert: the throw as it was made).
        arc_guard: while the needle is held in tissue, let it only turn about its own centre, the motion that
            strains no tissue (``lerobot_suture.safety.arc_guard``).
    """

    task: str | None = DEFAULT_TASK
    fps: int = 10
    episode_length: int | None = None
    obs_type: str = "pixels_agent_pos"
    image_size: int = 96
    render_size: int = 256
    scenario: str = "nominal"
    scenario_onset_step: int | None = None
    scenario_magnitude: float | None = None
    cbf: CBFConfig = field(default_factory=CBFConfig)
    appearance: AppearanceConfig = field(default_factory=AppearanceConfig)
    wrist_camera: bool = False
    marks: bool = False
    subtask: bool = False
    regrasp_target: bool = False
    regrasp_from: str = "marks"
    arc_guard: bool = False
    features: dict[str, PolicyFeature] = field(
        default_factory=lambda: {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(10,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(10,)),
        }
    )
    features_map: dict[str, str] = field(
        default_factory=lambda: {
            ACTION: ACTION,
            "agent_pos": OBS_STATE,
            "environment_state": OBS_ENV_STATE,
            ENDOSCOPE_KEY: f"{OBS_IMAGES}.endoscope",
            WRIST_KEY: f"{OBS_IMAGES}.wrist",
        }
    )

    def __post_init__(self):
        if self.fps != 10:
            raise ValueError(f"`fps` must be 10 (the env's control rate). Got {self.fps}.")
        if self.obs_type not in OBS_TYPES:
            raise ValueError(f"`obs_type` must be one of {OBS_TYPES}. Got {self.obs_type!r}.")
        if self.scenario not in SCENARIOS:
            raise ValueError(f"`scenario` must be one of {SCENARIOS}. Got {self.scenario!r}.")
        self.task = _TASK_BY_GYM_NAME.get(self.task, self.task or DEFAULT_TASK)
        spec = task_spec(self.task)
        check_scenario(self.task, self.scenario)
        if self.episode_length is None:
            self.episode_length = spec.max_episode_steps
        if self.episode_length < 1:
            raise ValueError(f"`episode_length` must be >= 1. Got {self.episode_length}.")
        check_image_side("image_size", self.image_size)
        check_image_side("render_size", self.render_size)
        check_regrasp_source(self.regrasp_from, self.regrasp_target, "--env.regrasp_target=true")
        if self.wrist_camera and "pixels" not in self.obs_type:
            raise ValueError(
                f"`wrist_camera` adds an image; `obs_type`={self.obs_type!r} has none. Pass "
                "--env.obs_type=pixels_agent_pos (or pixels_agent_pos_state)."
            )
        image = PolicyFeature(type=FeatureType.VISUAL, shape=(self.image_size, self.image_size, 3))
        if "pixels" in self.obs_type:
            self.features[ENDOSCOPE_KEY] = image
        if self.wrist_camera:
            self.features[WRIST_KEY] = image
        for name in STATE_PARTS:
            if getattr(self, name) and self.obs_type != "pixels_agent_pos":
                raise ValueError(
                    f"`{name}` adds to observation.environment_state; `obs_type`={self.obs_type!r} holds the "
                    "privileged state there. Pass --env.obs_type=pixels_agent_pos."
                )
        if self.obs_type in ("state", "pixels_agent_pos_state"):
            self.features["environment_state"] = PolicyFeature(
                type=FeatureType.ENV, shape=(PRIVILEGED_STATE_DIM,)
            )
        registered = state_size(name for name in STATE_PARTS if getattr(self, name))
        if registered:
            self.features["environment_state"] = PolicyFeature(type=FeatureType.ENV, shape=(registered,))

    @property
    def package_name(self) -> str:
        return "lerobot_suture"

    @property
    def gym_id(self) -> str:
        return task_spec(self.task).gym_id

    @property
    def gym_kwargs(self) -> dict:
        kwargs = {
            "obs_type": self.obs_type,
            "image_size": self.image_size,
            "render_mode": "rgb_array",
            "render_size": self.render_size,
            "scenario": self.scenario,
            "scenario_onset_step": self.scenario_onset_step,
            "scenario_magnitude": self.scenario_magnitude,
            "max_episode_steps": self.episode_length,
            "cbf": self.cbf if self.cbf.enabled else None,
        }
        if self.appearance.enabled:
            # Only when on, so that the default kwargs suit an env without the argument (an EnvHub
            # env.py run against an older lerobot_suture); a dict pickles to async workers as is.
            kwargs["appearance"] = dataclasses.asdict(self.appearance)
        if self.wrist_camera:
            kwargs["wrist_camera"] = True
        if self.marks:
            kwargs["marks"] = True
        if self.subtask:
            kwargs["subtask"] = True
        if self.regrasp_target:
            kwargs["regrasp_target"] = True
        if self.regrasp_from != "marks":
            kwargs["regrasp_from"] = self.regrasp_from
        if self.arc_guard:
            kwargs["arc_guard"] = True
        return kwargs
