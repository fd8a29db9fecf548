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
=============================  ==========================================  ========================
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

_DEFAULT_ONSET = {
    "nominal": 0,
    "needle_drop": 15,
    "camera_moved": 0,
    "phantom_servo": 8,
    "phantom_moved_after_insertion": 5,
}
_DEFAULT_MAGNITUDE = {
    "nominal": 0.0,
    "needle_drop": 0.0,
    "camera_moved": 0.6,
    "phantom_servo": 0.008,
    "phantom_moved_after_insertion": 0.006,
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
        name: one of :data:`SCENARIOS`.
        onset_step: control step at which the perturbation begins (for
            ``phantom_moved_after_insertion``: steps after the needle first enters tissue).
            None takes the scenario's default.
        magnitude: size of the perturbation (rad for ``camera_moved``, m for the phantom
            scenarios; unused by ``nominal`` and ``needle_drop``). None takes the default.
        glide_steps: control steps over which a phantom move is spread.
        period_steps: for ``phantom_servo``, control steps between successive moves.
    """

    name: str = "nominal"
    onset_step: int | None = None
    magnitude: float | None = None
    glide_steps: int = 6
    period_steps: int = 20

    def __post_init__(self):
        if self.name not in SCENARIOS:
            raise ValueError(f"`scenario` must be one of {SCENARIOS}. Got {self.name!r}.")
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


class Scenario:
    """Applies a :class:`ScenarioConfig` to an env; one instance per env, reset with it."""

    def __init__(self, config: ScenarioConfig):
        self.config = config
        self.perturbed = False
        self._glide: list[tuple[np.ndarray, float]] = []
        self._next_move_step = 0

    def reset(self, env: PerturbableEnv) -> None:
        self.perturbed = False
        self._glide = []
        self._next_move_step = self.config.onset_step
        self.before_step(env)

    def before_step(self, env: PerturbableEnv) -> None:
        """Apply the perturbation due at ``env.step_index`` (called before each control step)."""
        cfg = self.config
        step = env.step_index
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
            if not env.approach_over and step >= self._next_move_step and not self._glide:
                self._start_glide(env, within_training_range=True)
                self._next_move_step = step + cfg.period_steps
                self.perturbed = True
        elif cfg.name == "phantom_moved_after_insertion":
            first = env.first_in_tissue_step
            if first is not None and step >= first + cfg.onset_step and not self.perturbed:
                self._start_glide(env, within_training_range=False)
                self.perturbed = True
        if self._glide:
            position, yaw = self._glide.pop(0)
            env.set_phantom_pose(position, yaw)

    def _start_glide(self, env: PerturbableEnv, within_training_range: bool) -> None:
        rng = env.np_random
        start, yaw = env.phantom_position.copy(), env.phantom_yaw
        direction = rng.uniform(-math.pi, math.pi)
        goal = start.copy()
        goal[:2] += self.config.magnitude * np.array([math.cos(direction), math.sin(direction)])
        if within_training_range:
            goal[:2] = env.clip_to_phantom_range(goal[:2])
        n = self.config.glide_steps
        # Smooth (cosine) glide so the phantom does not jump between frames.
        for k in range(1, n + 1):
            s = 0.5 - 0.5 * math.cos(math.pi * k / n)
            self._glide.append((start + s * (goal - start), yaw))
