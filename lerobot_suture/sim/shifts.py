"""Distribution shifts beyond the paper's scenarios, each with a magnitude, for testing robustness and
the failure detectors on changes nobody tuned for (``lerobot-suture benchmark-ood``).

A shift is fixed for the whole episode (not drawn): it is what one operating room, one endoscope or one
arm does differently. :class:`ShiftWrapper` applies it to a suture env built by ``gym.make``, on top of
whatever the env itself does (its scenario, its appearance randomization, a CBF filter outside it).

=====================  ==========  ========  ===========================================================
shift                  family      unit      what a magnitude ``m`` does
=====================  ==========  ========  ===========================================================
``dim_light``          appearance  fraction  every light scaled by ``1 - m``
``smoke_haze``         appearance  fraction  a light grey veil of strength ``m`` over the image (smoke)
``instrument_colour``  appearance  fraction  the instrument's grey mixed by ``m`` towards blue
``tissue_colour``      appearance  turn      the tissue's hue turned by ``m`` of the colour circle
``camera_roll``        sensing     rad       the endoscope rolled by ``m`` about its optical axis
``image_noise``        sensing     fraction  Gaussian pixel noise, std ``m`` of full scale, every frame
``state_noise``        sensing     m         Gaussian noise of std ``m`` on the jaw position the policy
                                             reads (``agent_pos[:3]``), every step
``phantom_raised``     geometry    m         the phantom ``m`` higher than any training scene
``phantom_turned``     geometry    rad       the phantom turned ``m`` further about z than its drawn yaw
``action_delay``       dynamics    steps     each command executed ``m`` control steps late (latency)
=====================  ==========  ========  ===========================================================

:data:`MAGNITUDES` holds two magnitudes of each: the smaller one lies inside the appearance ranges of the
randomized recipe (``recipes/suture_expert_randomized.yaml``) where that recipe varies the quantity, the
larger one beyond them. Geometry and dynamics are not randomized by any recipe: both their magnitudes are
beyond training.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from lerobot_suture.sim.appearance import AppearanceSample


@dataclass(frozen=True)
class ShiftSpec:
    """One shift family: its name, kind, the unit of its magnitude and the largest magnitude allowed."""

    name: str
    family: str
    unit: str
    limit: float
    what: str


SHIFT_SPECS = {
    s.name: s
    for s in (
        ShiftSpec("dim_light", "appearance", "fraction", 0.95, "every light scaled by 1 - m"),
        ShiftSpec("smoke_haze", "appearance", "fraction", 0.9, "grey veil of strength m over the image"),
        ShiftSpec(
            "instrument_colour", "appearance", "fraction", 1.0, "instrument grey mixed by m towards blue"
        ),
        ShiftSpec("tissue_colour", "appearance", "turn", 0.5, "tissue hue turned by m"),
        ShiftSpec("camera_roll", "sensing", "rad", math.pi, "endoscope rolled by m about its axis"),
        ShiftSpec("image_noise", "sensing", "fraction", 0.25, "pixel noise, std m of full scale"),
        ShiftSpec("state_noise", "sensing", "m", 0.01, "noise of std m on the jaw position read"),
        ShiftSpec("phantom_raised", "geometry", "m", 0.02, "phantom m higher than in training"),
        ShiftSpec("phantom_turned", "geometry", "rad", 1.0, "phantom turned m further about z"),
        ShiftSpec("action_delay", "dynamics", "steps", 5, "commands executed m control steps late"),
    )
}
SHIFTS = tuple(SHIFT_SPECS)

MAGNITUDES: dict[str, tuple[float, float]] = {
    "dim_light": (0.2, 0.6),
    "smoke_haze": (0.2, 0.6),
    "instrument_colour": (0.15, 0.8),
    "tissue_colour": (0.03, 0.15),
    "camera_roll": (0.08, 0.3),
    "image_noise": (0.02, 0.1),
    "state_noise": (0.0005, 0.002),
    "phantom_raised": (0.003, 0.008),
    "phantom_turned": (0.2, 0.5),
    "action_delay": (1, 2),
}
"""Two magnitudes of each shift, the benchmark's default: (inside the randomized recipe's range where it
has one, beyond it)."""

RANDOMIZED_BY = {
    "dim_light": "light_intensity",
    "smoke_haze": "haze",
    "instrument_colour": "instrument_tint",
    "tissue_colour": "tissue_hue",
    "camera_roll": "camera_roll",
    "image_noise": "noise",
}
"""The appearance option (``AppearanceConfig``) whose range covers each shift; geometry, dynamics and the
state's noise are covered by none."""

_BLUE = 0.62  # hue (turns) the instrument is tinted towards: far from the grey and from the red tissue


@dataclass(frozen=True)
class Shift:
    """A shift family at one magnitude; ``Shift.parse("dim_light@0.6")`` reads the command-line form."""

    name: str
    magnitude: float

    def __post_init__(self):
        if self.name not in SHIFT_SPECS:
            raise ValueError(f"Unknown shift {self.name!r}; the shifts are {list(SHIFTS)}.")
        spec = SHIFT_SPECS[self.name]
        m = self.magnitude
        if isinstance(m, bool) or not (
            isinstance(m, (int, float)) and math.isfinite(m) and 0 < m <= spec.limit
        ):
            raise ValueError(
                f"Shift {self.name} needs a magnitude in (0, {spec.limit:g}] {spec.unit}. Got {m!r}."
            )
        if self.name == "action_delay" and float(m) != int(m):
            raise ValueError(f"Shift action_delay counts whole control steps. Got {m}.")

    @classmethod
    def parse(cls, text: str) -> Shift:
        name, sep, magnitude = text.partition("@")
        if not sep:
            raise ValueError(f"A shift is written NAME@MAGNITUDE (e.g. dim_light@0.6). Got {text!r}.")
        try:
            value = float(magnitude)
        except ValueError:
            raise ValueError(f"The magnitude of shift {text!r} is not a number.") from None
        return cls(name, value)

    @property
    def label(self) -> str:
        return f"{self.name}@{self.magnitude:g}"

    @property
    def family(self) -> str:
        return SHIFT_SPECS[self.name].family

    def appearance(self) -> AppearanceSample | None:
        """The fixed look this shift shows, None for a shift that leaves the image alone."""
        m = float(self.magnitude)
        looks = {
            "dim_light": AppearanceSample(light_scale=1.0 - m),
            "smoke_haze": AppearanceSample(haze=m),
            "instrument_colour": AppearanceSample(instrument_tint_hue=_BLUE, instrument_tint=m),
            "tissue_colour": AppearanceSample(tissue_hue_shift=m),
            "camera_roll": AppearanceSample(camera_roll=m),
            "image_noise": AppearanceSample(noise_std=m),
        }
        return looks.get(self.name)


def within_training_range(shift: Shift, appearance: dict | None) -> bool | None:
    """Whether ``shift``'s magnitude lies inside the range a dataset's appearance randomization
    (``appearance``, the fields of an ``AppearanceConfig``; None: none) drew from: True inside, False
    beyond, None when no option of it covers this shift at all."""
    option = RANDOMIZED_BY.get(shift.name)
    if option is None or not appearance or not appearance.get(option):
        return None
    return float(shift.magnitude) <= float(appearance[option])


def default_shifts() -> list[Shift]:
    """Every shift at both of its :data:`MAGNITUDES`."""
    return [Shift(name, m) for name in SHIFTS for m in MAGNITUDES[name]]


class ShiftWrapper(gym.Wrapper):
    """A suture env under one :class:`Shift`, from the first observation of every episode on.

    A shift that changes the first image or the phantom re-reads the observation from the env itself
    (``SutureEnv.observe``), so the wrappers under this one must leave observations as the env makes them
    (gym's own, the CBF's). An appearance shift shows its look in place of the one the env's appearance
    randomization drew.

    Args:
        env: a suture env (``gym.make`` of ``lerobot_suture/NeedleInsertion-v0``, possibly wrapped).
        shift: the shift and its magnitude.
    """

    def __init__(self, env: gym.Env, shift: Shift):
        super().__init__(env)
        self.shift = shift
        self._delayed: deque = deque()
        self._noise_rng = np.random.default_rng(0)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        u = self.env.unwrapped
        look = self.shift.appearance()
        m = float(self.shift.magnitude)
        if look is not None:
            u.set_appearance(look)
        elif self.shift.name == "phantom_raised":
            u.set_phantom_pose(u.phantom_position + np.array([0.0, 0.0, m]), u.phantom_yaw)
        elif self.shift.name == "phantom_turned":
            u.set_phantom_pose(u.phantom_position, u.phantom_yaw + m)
        if look is not None or self.shift.name.startswith("phantom_"):
            obs = u.observe()
        # The noise of the state is the episode's own: a seed gives the same noise.
        self._noise_rng = np.random.default_rng(None if seed is None else [0x5E5, int(seed)])
        # The commands before the first delayed one hold the jaw where it is.
        hold = np.asarray(obs["agent_pos"], dtype=np.float32).copy()
        self._delayed = (
            deque([hold] * int(self.shift.magnitude)) if self.shift.name == "action_delay" else deque()
        )
        return self._sense(obs), info

    def step(self, action):
        if self.shift.name == "action_delay":
            self._delayed.append(np.asarray(action, dtype=np.float32).copy())
            action = self._delayed.popleft()
        obs, reward, terminated, truncated, info = self.env.step(action)
        return self._sense(obs), reward, terminated, truncated, info

    def _sense(self, obs: dict) -> dict:
        if self.shift.name != "state_noise":
            return obs
        noisy = np.asarray(obs["agent_pos"], dtype=np.float32).copy()
        noisy[:3] += self._noise_rng.normal(0.0, self.shift.magnitude, size=3).astype(np.float32)
        return {**obs, "agent_pos": noisy}
