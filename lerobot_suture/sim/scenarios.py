"""The paper's perturbation scenarios, applied to a running :class:`~lerobot_suture.sim.suture_env.SutureEnv`.

Each scenario has an onset (control step) and a magnitude; ``perturbed`` becomes True on the step
the perturbation begins, so detection delay can be measured from it.

=============================  ==========================================  ========================
name                           what happens                                 magnitude (default)
=============================  ==========================================  ========================
``nominal``                    nothing                                      --
``needle_drop``                the jaw loses the needle ``onset_step``      -- (onset 15)
                               steps after it first holds it (at once in
                               ``insertion``); it falls under gravity
``camera_moved``               from ``onset_step`` the endoscope views the   azimuth shift, rad
                               site from outside the training viewpoints     (0.6; onset 0)
``phantom_servo``              during the approach the phantom glides to a   displacement, m
                               new pose inside the training range, every     (0.008; onset 8)
                               ``period_steps`` until the approach is over
                               (``approach_over``)
``phantom_moved_after_insertion``  ``onset_step`` steps after the needle      displacement, m
                               first enters tissue the phantom glides away   (0.006; onset 5)
``breathing``                  from ``onset_step`` the phantom rises and     amplitude, m
                               falls along its normal, a sinusoid of         (0.0025; onset 0)
                               ``breathing_frequency`` (0.25 Hz)
=============================  ==========================================  ========================

``SCENARIOS`` are the paper's, the conditions of its experiments and of the leaderboard; ``breathing`` is one of
``SAFETY_SCENARIOS``, the motions the safety benchmarks add, and applies to every task with a throw. Its default,
5 mm peak to peak at 15 breaths a minute, lies in the few millimetres at 12-20 breaths a minute reported for
abdominal tissue under ventilation.

The phantom moves continuously: a glide follows a cosine profile over ``glide_steps`` control steps, and the
env places the phantom at every physics step (:meth:`Scenario.phantom_pose`), so no physics step sees it jump.
A glide of displacement ``D`` over ``T`` s peaks at ``pi D / (2 T)`` m/s and ``pi^2 D / (2 T^2)`` m/s^2; the
default 1.5 s keeps the default displacements within 9 mm/s and 18 mm/s^2. Breathing of amplitude ``A`` at
``f`` Hz peaks at ``2 pi f A`` m/s and ``(2 pi f)^2 A`` m/s^2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

SCENARIOS = (
    "nominal",
    "needle_drop",
    "camera_moved",
    "phantom_servo",
    "phantom_moved_after_insertion",
)
SAFETY_SCENARIOS = ("breathing",)
"""Tissue motions the safety benchmarks add to the paper's scenarios (tasks with a throw)."""

_DEFAULT_ONSET = {
    "nominal": 0,
    "needle_drop": 15,
    "camera_moved": 0,
    "phantom_servo": 8,
    "phantom_moved_after_insertion": 5,
    "breathing": 0,
}
_DEFAULT_MAGNITUDE = {
    "nominal": 0.0,
    "needle_drop": 0.0,
    "camera_moved": 0.6,
    "phantom_servo": 0.008,
    "phantom_moved_after_insertion": 0.006,
    "breathing": 0.0025,
}


class PerturbableEnv(Protocol):
    """What a scenario reads from and moves in the env; ``SutureEnv`` is one.

    Stated here, rather than imported from ``suture_env``, so that imports run one way: the env
    holds a :class:`Scenario`, and this module needs nothing of the env's but these members.
    """

    np_random: np.random.Generator

    @property
    def step_index(self) -> int: ...

    @property
    def phantom_position(self) -> np.ndarray: ...

    @property
    def phantom_yaw(self) -> float: ...

    @property
    def approach_over(self) -> bool: ...

    @property
    def first_grasp_step(self) -> int | None: ...

    @property
    def first_in_tissue_step(self) -> int | None: ...

    def release_needle(self) -> None: ...

    def set_phantom_pose(self, position: np.ndarray, yaw: float) -> None: ...

    def clip_to_phantom_range(self, xy: np.ndarray) -> np.ndarray: ...

    def set_endoscope_viewpoint(self, azimuth_offset: float = 0.0, elevation_offset: float = 0.0) -> None: ...


@dataclass
class ScenarioConfig:
    """A perturbation scenario.

    Args:
        name: one of :data:`SCENARIOS` or :data:`SAFETY_SCENARIOS`.
        onset_step: control step at which the perturbation begins (for
            ``phantom_moved_after_insertion``: steps after the needle first enters tissue).
            None takes the scenario's default.
        magnitude: size of the perturbation (rad for ``camera_moved``, m for the phantom
            scenarios; unused by ``nominal`` and ``needle_drop``). None takes the default.
        glide_steps: control steps over which a phantom move is spread.
        period_steps: for ``phantom_servo``, control steps between successive moves.
        breathing_frequency: for ``breathing``, breaths per second (Hz, > 0).
    """

    name: str = "nominal"
    onset_step: int | None = None
    magnitude: float | None = None
    glide_steps: int = 15
    period_steps: int = 20
    breathing_frequency: float = 0.25

    def __post_init__(self):
        if self.name not in SCENARIOS + SAFETY_SCENARIOS:
            raise ValueError(f"`scenario` must be one of {SCENARIOS + SAFETY_SCENARIOS}. Got {self.name!r}.")
        if self.onset_step is None:
            self.onset_step = _DEFAULT_ONSET[self.name]
        if self.magnitude is None:
            self.magnitude = _DEFAULT_MAGNITUDE[self.name]
        if self.onset_step < 0:
            raise ValueError(f"`scenario_onset_step` must be >= 0. Got {self.onset_step}.")
        if self.magnitude < 0 or not math.isfinite(self.magnitude):
            raise ValueError(f"`scenario_magnitude` must be finite and >= 0. Got {self.magnitude}.")
        if self.glide_steps < 1 or self.period_steps < 1:
            raise ValueError(
                f"`glide_steps` and `period_steps` must be >= 1. Got {self.glide_steps}, {self.period_steps}."
            )
        if not 0.0 < self.breathing_frequency <= 5.0:
            raise ValueError(f"`breathing_frequency` must be in (0, 5] Hz. Got {self.breathing_frequency}.")


@dataclass
class _Glide:
    """One phantom move: from ``start`` to ``goal`` (m) over ``duration`` s from ``t0`` s, cosine profile."""

    t0: float
    duration: float
    start: np.ndarray
    goal: np.ndarray

    def offset(self, t: float) -> np.ndarray:
        s = min(max((t - self.t0) / self.duration, 0.0), 1.0)
        return (0.5 - 0.5 * math.cos(math.pi * s)) * (self.goal - self.start)

    def over(self, t: float) -> bool:
        return t >= self.t0 + self.duration


class Scenario:
    """Applies a :class:`ScenarioConfig` to an env; one instance per env, reset with it.

    Args:
        config: the scenario. control_dt: the env's control period (s), the clock of onsets and glides.
    """

    def __init__(self, config: ScenarioConfig, control_dt: float = 0.1):
        self.config = config
        self.control_dt = float(control_dt)
        self.perturbed = False
        self._glide: _Glide | None = None
        self._base: tuple[np.ndarray, float] | None = None  # phantom pose the motion is relative to
        self._breathing_t0: float | None = None
        self._next_move_step = 0

    def reset(self, env: PerturbableEnv) -> None:
        self.perturbed = False
        self._glide = None
        self._base = None
        self._breathing_t0 = None
        self._next_move_step = self.config.onset_step
        self.before_step(env)

    @property
    def moving(self) -> bool:
        """The phantom is in motion (a glide under way, or breathing)."""
        return self._glide is not None or self._breathing_t0 is not None

    def phantom_pose(self, t: float) -> tuple[np.ndarray, float]:
        """Where the phantom is at time ``t`` (s since the episode began) while :attr:`moving`: position (3,) m
        and yaw rad."""
        position, yaw = self._base
        position = position.copy()
        if self._glide is not None:
            position += self._glide.offset(t)
        if self._breathing_t0 is not None:
            phase = 2.0 * math.pi * self.config.breathing_frequency * (t - self._breathing_t0)
            position[2] += self.config.magnitude * math.sin(max(phase, 0.0))
        return position, yaw

    def before_step(self, env: PerturbableEnv) -> None:
        """Apply the perturbation due at ``env.step_index`` (called before each control step); a motion it
        starts is placed by the env at every physics step through :meth:`phantom_pose`."""
        cfg = self.config
        step = env.step_index
        t = step * self.control_dt
        if self._glide is not None and self._glide.over(t):
            self._base = (self._glide.goal.copy(), self._base[1])
            self._glide = None
        if cfg.name == "needle_drop":
            first = env.first_grasp_step
            if first is not None and step >= first + cfg.onset_step and not self.perturbed:
                env.release_needle()
                self.perturbed = True
        elif cfg.name == "camera_moved":
            if step >= cfg.onset_step and not self.perturbed:
                # Orbit the endoscope sideways and lower it: a viewpoint never seen in training.
                env.set_endoscope_viewpoint(
                    azimuth_offset=cfg.magnitude, elevation_offset=-0.25 * cfg.magnitude
                )
                self.perturbed = True
        elif cfg.name == "phantom_servo":
            if not env.approach_over and step >= self._next_move_step and self._glide is None:
                self._start_glide(env, t, within_training_range=True)
                self._next_move_step = step + cfg.period_steps
                self.perturbed = True
        elif cfg.name == "phantom_moved_after_insertion":
            first = env.first_in_tissue_step
            if first is not None and step >= first + cfg.onset_step and not self.perturbed:
                self._start_glide(env, t, within_training_range=False)
                self.perturbed = True
        elif cfg.name == "breathing":
            if step >= cfg.onset_step and not self.perturbed:
                self._base = (env.phantom_position.copy(), env.phantom_yaw)
                self._breathing_t0 = t
                self.perturbed = True

    def _start_glide(self, env: PerturbableEnv, t: float, within_training_range: bool) -> None:
        rng = env.np_random
        start = env.phantom_position.copy()
        self._base = (start, env.phantom_yaw)
        direction = rng.uniform(-math.pi, math.pi)
        goal = start.copy()
        goal[:2] += self.config.magnitude * np.array([math.cos(direction), math.sin(direction)])
        if within_training_range:
            goal[:2] = env.clip_to_phantom_range(goal[:2])
        self._glide = _Glide(t, self.config.glide_steps * self.control_dt, start, goal)
