"""The registered wound as an observation: the current throw's entry and exit marks (opt-in, ``marks=True``).

A surgical system that tracks the wound has the marks where its hand-eye calibration puts them: in the arm's
base frame, the frame its pose targets are in (the world frame here, as for ``agent_pos`` and the action).
The robot path reports the same points with ``--robot.registration=true``. On the running suture the marks
move to the next throw's pair once the needle of a throw has been extracted. Nothing else of the simulator's
state is exposed: the needle's pose stays a training target only.

:class:`WoundMarks` adds them to an env's observation as ``environment_state`` (6,) float32 (entry x, y, z,
exit x, y, z, m), which LeRobot maps to ``observation.environment_state``, a state input of ACT, diffusion and
the ensemble. The physics, the images and ``agent_pos`` are unchanged.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

MARKS_KEY = "environment_state"
MARKS_DIM = 6
MARKS_NAMES = ("entry_x", "entry_y", "entry_z", "exit_x", "exit_y", "exit_z")
"""The marks' components (m, the arm's base frame): the dataset feature's names."""


def wound_marks(env) -> np.ndarray:
    """(6,) float32: the current throw's entry and exit marks of ``env`` (m, world frame)."""
    base = env.unwrapped
    return np.concatenate([base.entry_point, base.exit_point]).astype(np.float32)


class WoundMarks(gym.ObservationWrapper):
    """``env``'s observation plus the current throw's marks as ``environment_state`` (see the module docstring).

    Raises:
        ValueError: the observation already has an ``environment_state`` (the privileged ``obs_type``\\ s).
    """

    def __init__(self, env: gym.Env):
        if MARKS_KEY in env.observation_space.spaces:
            raise ValueError(
                "`marks` adds the wound's marks as environment_state; obs_type="
                f"{env.unwrapped.obs_type!r} already holds the privileged one. Pass obs_type='pixels_agent_pos'."
            )
        super().__init__(env)
        self.observation_space = spaces.Dict(
            {
                **env.observation_space.spaces,
                MARKS_KEY: spaces.Box(-np.inf, np.inf, (MARKS_DIM,), dtype=np.float32),
            }
        )

    def observation(self, observation: dict) -> dict:
        return {**observation, MARKS_KEY: wound_marks(self.env)}
