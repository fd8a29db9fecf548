"""``SutureSim``: the suturing scene of ``lerobot_suture`` as a LeRobot robot.

The scene is the Gymnasium env of ``--robot.task`` (``lerobot_suture/NeedleInsertion-v0`` by default;
``lerobot_suture.sim.suture_env``),
made with ``gym.make`` (behind the CBF safety filter when ``--robot.cbf.enabled=true``): the same physics
that ``lerobot-eval --env.type=suture`` and the expert recordings run.

- ``get_observation()``: ``{"endoscope": (H, W, 3) uint8, "x.pos": ..., ..., "jaw.pos": ...}``, the
  endoscope image and the measured pose of the needle holder (the env's ``agent_pos``);
  ``--robot.wrist_camera=true`` adds ``"wrist"``, the image of a camera on the instrument's shaft;
  ``--robot.marks=true`` the current throw's entry and exit marks (``entry_x.pos`` ... ``exit_z.pos``, m);
  ``--robot.regrasp_target=true`` the regrasp planned through them, in the jaw frame (``regrasp_dx.pos`` ...).
- ``send_action({"x.pos": ..., ..., "jaw.pos": ...})``: the target pose of the needle holder; the env steps
  one control period (0.1 s, 50 physics steps) towards it. Returns the target clipped to the action space.
- ``--robot.registration=true`` adds the registered wound and the needle in the jaw to the observation (what
  the ``suture_cbf`` step reads); ``--robot.faults.*`` passes the observation and the command through the faults
  of :mod:`.faults` (computed once per control step, so any number of ``get_observation`` calls agree).
- Episodes: when LeRobot starts dataset episode N (``lerobot-record``, the episodic and gated DAgger
  strategies) the scene is that of ``seed + N``; when the episode ends, the next seed's scene is reset and
  held until the next episode starts (:func:`lerobot_suture.lerobot_shim.install_episode_hooks`, which
  :meth:`SutureSim.connect` installs; ``docs/robot.md``).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass
from functools import cached_property

import gymnasium as gym
import numpy as np
from lerobot.lerobot_types import RobotAction, RobotObservation
from lerobot.robots.robot import Robot
from lerobot.utils.decorators import check_if_already_connected, check_if_not_connected

from lerobot_suture.lerobot_shim import install_episode_hooks
from lerobot_suture.sim.regrasp_target import STATE_KEY
from lerobot_suture.sim.state_layout import part_slices
from lerobot_suture.sim.task import CONTROL_DT
from lerobot_suture.sim.tasks import task_spec

from . import link
from .cbf_step import GRASP_FEATURES, THROW_FEATURE, WOUND_FEATURES
from .clock import ControlClock
from .config_suture_sim import (
    CAMERA,
    MARK_FEATURES,
    POSE_FEATURES,
    REGRASP_TARGET_FEATURES,
    WRIST_CAMERA,
    SutureSimConfig,
)
from .faults import FaultInjector

logger = logging.getLogger(__name__)

FPS = round(1.0 / CONTROL_DT)
"""The arm's control rate (10 Hz): record and replay its datasets at ``--dataset.fps=10``."""
END_EFFECTOR_COMMAND_KEYS = ("delta_x", "delta_y", "delta_z")
_PART_FEATURES = {"marks": MARK_FEATURES, "regrasp_target": REGRASP_TARGET_FEATURES}
"""The env's ``environment_state`` parts a robot reports (its config's flags), in the env's order, with their
feature names."""


@dataclass(frozen=True)
class SimulatedCamera:
    """The endoscope's size; LeRobot sizes its image writers by ``len(robot.cameras)``."""

    height: int
    width: int
    fps: int = FPS


class SutureSim(Robot):
    """The simulated da Vinci-style arm holding a suture needle over a phantom, seen by an endoscope."""

    config_class = SutureSimConfig
    name = "suture_sim"

    def __init__(self, config: SutureSimConfig):
        super().__init__(config)
        self.config = config
        cameras = (CAMERA, WRIST_CAMERA) if config.wrist_camera else (CAMERA,)
        self.cameras = {name: SimulatedCamera(config.image_size, config.image_size) for name in cameras}
        self.task = task_spec(config.task).instruction
        """The task in words (pass it as ``--dataset.single_task``)."""
        self.env: gym.Env | None = None
        self._lock = threading.RLock()
        self._clock = ControlClock(CONTROL_DT, realtime=config.clock == "realtime")
        self._trace = None
        self._obs: dict | None = None
        self._faults = FaultInjector(
            config.faults,
            camera_key=CAMERA,
            pose_keys=tuple(POSE_FEATURES),
            derived_keys=tuple(REGRASP_TARGET_FEATURES) if config.regrasp_target else (),
        )
        self._observed: dict | None = None
        self.last_info: dict = {}
        """The env's ``info`` of the last reset or step (``is_success``, ``needle_tip_pos``, ...)."""
        self.scene_seed: int | None = None
        self.scene_steps = 0
        """Control steps executed in the current scene."""
        self.scene_count = 0
        """Scenes started since ``connect`` (a teleoperator re-anchors its target when it changes)."""
        self.total_steps = 0
        """Control steps executed since ``connect``, over all scenes."""
        self.holding = False
        """In LeRobot's reset phase: the new scene is held and actions are not executed."""
        self.scene_over = False
        """With ``episode_end=hold``: the scene's episode has ended, the arm holds its last pose and actions
        are not executed until the next scene."""
        self._episode: int | None = None

    # ------------------------------------------------------------------ features
    @cached_property
    def observation_features(self) -> dict[str, type | tuple]:
        size = self.config.image_size
        images = dict.fromkeys(self.cameras, (size, size, 3))
        registered = [feature for part in self._registered_parts for feature in _PART_FEATURES[part]]
        return {
            **dict.fromkeys([*POSE_FEATURES, *registered], float),
            **images,
            **self._registration_features,
        }

    @cached_property
    def _registered_parts(self) -> tuple[str, ...]:
        """The env's ``environment_state`` parts this robot reports, in the env's order."""
        return tuple(part for part in _PART_FEATURES if getattr(self.config, part))

    @cached_property
    def _registration_features(self) -> dict[str, type]:
        if not self.config.registration:
            return {}
        wound = (*WOUND_FEATURES, THROW_FEATURE) if task_spec(self.config.task).throws > 0 else ()
        return dict.fromkeys((*wound, *GRASP_FEATURES), float)

    @cached_property
    def action_features(self) -> dict[str, type]:
        return dict.fromkeys(POSE_FEATURES, float)

    # ------------------------------------------------------------------ connection
    @property
    def is_connected(self) -> bool:
        return self.env is not None

    @check_if_already_connected
    def connect(self, calibrate: bool = True) -> None:
        if not self.is_calibrated and calibrate:
            self.calibrate()
        self.env = gym.make(self.config.gym_id, disable_env_checker=True, **self.config.env_kwargs())
        if self.config.trace_path is not None:
            self.config.trace_path.parent.mkdir(parents=True, exist_ok=True)
            self._trace = open(self.config.trace_path, "a", buffering=1)  # noqa: SIM115 - closed at disconnect
        self._episode = None
        self.holding = False
        self._reset_scene(self.config.seed)
        self.configure()
        install_episode_hooks()
        link.register(self)
        logger.info("%s connected: scene seed %d, %s clock.", self, self.config.seed, self.config.clock)

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        logger.info("%s: nothing to calibrate; the simulated arm measures its pose exactly.", self)

    def configure(self) -> None:
        pass

    @check_if_not_connected
    def disconnect(self) -> None:
        link.unregister(self)
        with self._lock:
            self.env.close()
            self.env = None
            if self._trace is not None:
                self._trace.close()
                self._trace = None
        logger.info("%s disconnected.", self)

    # ------------------------------------------------------------------ I/O
    @check_if_not_connected
    def get_observation(self) -> RobotObservation:
        with self._lock:
            return dict(self._observed)

    @check_if_not_connected
    def send_action(self, action: RobotAction) -> RobotAction:
        target = self._target(action)
        with self._lock:
            if self.holding or self.scene_over:
                return dict(zip(POSE_FEATURES, target.tolist(), strict=True))
            space = self.env.unwrapped.action_space
            sent = np.clip(target, space.low, space.high)
            self._clock.tick()
            executed = self._faults.command(sent, np.asarray(self._obs["agent_pos"], dtype=np.float64))
            obs, _reward, terminated, truncated, info = self.env.step(executed)
            self._obs, self.last_info = obs, info
            self._observe()
            self.scene_steps += 1
            self.total_steps += 1
            self.scene_over = self.config.episode_end == "hold" and bool(terminated or truncated)
            self._write_trace(sent, terminated, truncated)
            return dict(zip(POSE_FEATURES, sent.astype(float).tolist(), strict=True))

    # ------------------------------------------------------------------ what else a caller may read
    def measured_pose(self) -> np.ndarray:
        """(10,) float64 measured pose of the needle holder (the observation's state)."""
        with self._lock:
            return np.asarray(self._obs["agent_pos"], dtype=np.float64).copy()

    @property
    def needle_tip(self) -> np.ndarray:
        """(3,) needle tip position (m, world) after the last reset or step."""
        return np.asarray(self.last_info["needle_tip_pos"], dtype=np.float64).copy()

    def reset_scene(self, seed: int) -> None:
        """Start the scene of ``seed`` now (what the start of a dataset episode does for ``seed + N``)."""
        with self._lock:
            self.holding = False
            self._reset_scene(seed)

    # ------------------------------------------------------------------ internals
    def _observe(self) -> None:
        """What the arm reports for the state it is in now, through the configured faults (once per step)."""
        pose = self._obs["agent_pos"]
        observation: dict = {name: float(v) for name, v in zip(POSE_FEATURES, pose, strict=True)}
        for part, where in part_slices(self._registered_parts).items():
            values = map(float, self._obs[STATE_KEY][where])
            observation.update(zip(_PART_FEATURES[part], values, strict=True))
        for name in self.cameras:  # the env's pixels carry the same names
            observation[name] = self._obs["pixels"][name]
        observation.update(self._registration())
        self._observed = self._faults.observe(observation)

    def _registration(self) -> dict[str, float]:
        """The registered wound and the needle in the jaw, where ``registration`` is on (exact here)."""
        features = self._registration_features
        if not features:
            return {}
        base = self.env.unwrapped
        values = {
            **dict(zip(GRASP_FEATURES, base.grasp_parameters, strict=True)),
            THROW_FEATURE: base.throw_index,
        }
        wound = np.concatenate([base.entry_point, base.exit_point, base.phantom_rotation[:, 2]])
        values.update(zip(WOUND_FEATURES, wound, strict=True))
        return {key: float(values[key]) for key in features}

    @staticmethod
    def _target(action: RobotAction) -> np.ndarray:
        missing = [name for name in POSE_FEATURES if name not in action]
        if missing:
            if any(key in action for key in END_EFFECTOR_COMMAND_KEYS):
                raise ValueError(
                    "suture_sim takes a target pose, not an end-effector command (delta_x, ...). Drive it "
                    "with --teleop.type=suture_keyboard or --teleop.type=suture_gamepad, which turn LeRobot's "
                    "keyboard and gamepad commands into target poses."
                )
            raise ValueError(f"suture_sim's action lacks {missing}; it needs {POSE_FEATURES}.")
        return np.array([float(action[name]) for name in POSE_FEATURES], dtype=np.float64)

    def _reset_scene(self, seed: int) -> None:
        self._obs, self.last_info = self.env.reset(seed=int(seed))
        self._faults.reset(int(seed))
        self._observe()
        self.scene_seed = int(seed)
        self.scene_steps = 0
        self.scene_over = False
        self.scene_count += 1
        self._clock.restart()

    # ------------------------------------------------------------------ episodes (lerobot_shim.EpisodeAware)
    @check_if_not_connected
    def start_episode(self, episode: int) -> None:
        """LeRobot starts dataset episode ``episode``: its scene is that of ``seed + episode``, fresh."""
        seed = self.config.seed + episode
        with self._lock:
            self._episode = episode
            self.holding = False
            if not (self.scene_seed == seed and self.scene_steps == 0):
                self._reset_scene(seed)
            logger.info("%s: episode %d on the scene of seed %d.", self, episode, seed)

    @check_if_not_connected
    def end_episode(self) -> None:
        """The episode ended: the next episode's scene, held until that episode starts (LeRobot's reset phase,
        a teleoperator's and the episodic strategy's return to the initial position are not executed)."""
        with self._lock:
            episode = self._episode if self._episode is not None else self.scene_seed - self.config.seed
            self._reset_scene(self.config.seed + episode + 1)
            self.holding = True
            logger.info("%s: scene reset to seed %d and held for the reset phase.", self, self.scene_seed)

    def _write_trace(self, sent: np.ndarray, terminated: bool, truncated: bool) -> None:
        if self._trace is None:
            return
        info = self.last_info
        line = {
            "seed": self.scene_seed,
            "step": self.scene_steps,
            "action": sent.tolist(),
            "pose": np.asarray(self._obs["agent_pos"], dtype=float).tolist(),
            "needle_tip": np.asarray(info["needle_tip_pos"], dtype=float).tolist(),
            "is_success": bool(info["is_success"]),
            "throw_over": bool(terminated),
            "time_limit": bool(truncated),
            "wall_time": time.perf_counter(),  # s, when the step ended: the loop's period and jitter
            "needle_in_tissue": bool(info["needle_in_tissue"]),
            "needle_grasped": bool(info["needle_grasped"]),
        }
        self._trace.write(json.dumps(line) + "\n")
