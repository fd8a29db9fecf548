"""Actions relative to the jaw's measured pose (opt-in, ``relative_actions=True``): each step's motion in the jaw frame.

The env's own action is the target jaw pose in the arm's base frame. A policy that outputs it must place the
jaw to a fraction of a millimetre across a workspace of centimetres, and LeRobot normalizes each action
dimension over its range in the dataset: an error of 1% of the normalized position is about 0.5 mm, and a
pull whose target jitters by that much drags the needle off its arc at every step (the extraction's tissue
strain sums that motion, ``studies/benchmarks/strain_tolerance.py``). Here the action is the motion from the
jaw's measured pose to the target, in the jaw's own frame: the position change (3, m), the first two columns
of the rotation change (6) and the jaw command (1, absolute: 1 = closed). A step moves at most 5 mm (the
arm's speed limit), so the same normalized error is at least ten times smaller; and a pull about the needle's
centre, constant in the jaw frame, is the same action at every step. The surgical robot transformer (SRT) on
the dVRK learns relative motions too, there because the arm's absolute kinematics are inconsistent.

:class:`RelativeActions` turns such an action into the env's absolute target (``absolute_action``) before the
env steps it, so the controller, the CBF at the needle tip and every safety check see what they see for an
absolute action; :func:`relative_action` is the inverse, for whoever computes an absolute target (the
scripted expert while recording, the scripted surgeon). Composition then inversion is exact to float
precision, so a recorded episode replays to the same targets.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from lerobot_suture.sim.geometry import POSE_DIM, matrix_from_rot6, rot6_from_matrix

MAX_RELATIVE_STEP = 0.01
"""The largest position change a relative action may ask for (m, per axis of the jaw frame): twice what
the arm moves in one control step at its speed limit; larger requests are clipped to it."""
RELATIVE_ACTION_NAMES = ("dx", "dy", "dz", "dr11", "dr21", "dr31", "dr12", "dr22", "dr32", "jaw")
"""A relative action's components: position change in the jaw frame (m), first two columns of the rotation
change, jaw closure (1 = closed): the dataset feature's names."""


def absolute_action(jaw_pos: np.ndarray, jaw_rot: np.ndarray, relative: np.ndarray) -> np.ndarray:
    """The absolute target (10,) float64 that ``relative`` asks for from the jaw pose ``jaw_pos`` (3,) m,
    ``jaw_rot`` (3, 3).

    Raises:
        ValueError: the rotation change's two columns are zero or parallel (as for an absolute action).
    """
    relative = np.asarray(relative, dtype=np.float64)
    out = np.empty(POSE_DIM)
    out[:3] = jaw_pos + jaw_rot @ relative[:3]
    out[3:9] = rot6_from_matrix(jaw_rot @ matrix_from_rot6(relative[3:9]))
    out[9] = relative[9]
    return out


def relative_action(jaw_pos: np.ndarray, jaw_rot: np.ndarray, absolute: np.ndarray) -> np.ndarray:
    """The relative action (10,) float64 that reaches the absolute target ``absolute`` from the jaw pose
    ``jaw_pos`` (3,) m, ``jaw_rot`` (3, 3): the inverse of :func:`absolute_action`."""
    absolute = np.asarray(absolute, dtype=np.float64)
    out = np.empty(POSE_DIM)
    out[:3] = jaw_rot.T @ (absolute[:3] - jaw_pos)
    out[3:9] = rot6_from_matrix(jaw_rot.T @ matrix_from_rot6(absolute[3:9]))
    out[9] = absolute[9]
    return out


RELATIVE_LOW = np.concatenate([np.full(3, -MAX_RELATIVE_STEP), -np.ones(6), [0.0]])
RELATIVE_HIGH = np.concatenate([np.full(3, MAX_RELATIVE_STEP), np.ones(6), [1.0]])
"""Bounds of a relative action (10,): the position change to :data:`MAX_RELATIVE_STEP` per axis, the rotation
columns to [-1, 1] and the jaw to [0, 1], as the absolute action's."""


def target_from_relative(jaw_pos: np.ndarray, jaw_rot: np.ndarray, relative: np.ndarray) -> np.ndarray:
    """The absolute target (10,) float64 a policy's relative action asks for from the jaw pose ``jaw_pos``
    (3,) m, ``jaw_rot`` (3, 3): the action clipped to :data:`RELATIVE_LOW` .. :data:`RELATIVE_HIGH`, then
    composed (:func:`absolute_action`). A non-finite action is returned as it is, for the env's own check to
    name its bad entries.

    Raises:
        ValueError: ``relative`` is not of shape (10,).
    """
    a = np.asarray(relative, dtype=np.float64)
    if a.shape != (POSE_DIM,):
        raise ValueError(
            f"a relative action must have shape ({POSE_DIM},) (position change 3, rotation change columns 6, "
            f"jaw 1). Got shape {a.shape}."
        )
    if not np.all(np.isfinite(a)):
        return a
    return absolute_action(jaw_pos, jaw_rot, np.clip(a, RELATIVE_LOW, RELATIVE_HIGH))


STILL_MOTION = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0])
"""The motion part (9,) of a relative action that keeps the jaw where it is: no position change, the identity
rotation's columns; the jaw command follows it."""


def find_relative_actions(env: gym.Env) -> RelativeActions | None:
    """The :class:`RelativeActions` wrapper in ``env``'s chain of wrappers, or None."""
    while isinstance(env, gym.Wrapper):
        if isinstance(env, RelativeActions):
            return env
        env = env.env
    return None


def env_action(env: gym.Env, absolute: np.ndarray) -> np.ndarray:
    """What ``env.step`` must receive to reach the absolute target ``absolute``: the relative action when
    ``env`` has relative actions, else ``absolute`` itself (float32)."""
    wrapper = find_relative_actions(env)
    if wrapper is None:
        return np.asarray(absolute, dtype=np.float32)
    return wrapper.relative(absolute)


def measured_jaw(agent_pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The jaw pose an observation's ``agent_pos`` (10,) reports: position (3,) m and rotation (3, 3), float64."""
    pose = np.asarray(agent_pos, dtype=np.float64)
    return pose[:3], matrix_from_rot6(pose[3:9])


class RelativeActions(gym.Wrapper):
    """``env`` driven by actions relative to the jaw's measured pose (see the module docstring).

    The action space is :data:`RELATIVE_LOW` .. :data:`RELATIVE_HIGH`; each action becomes its target with
    :func:`target_from_relative`, from the pose the last observation reported (``agent_pos``, as the robot
    measures it), so a recorded label and a trained policy's post-processor compose from the same numbers. A
    trained policy does not need this wrapper: its post-processor hands any env or robot absolute targets.
    """

    def __init__(self, env: gym.Env):
        super().__init__(env)
        self.action_space = spaces.Box(
            low=RELATIVE_LOW.astype(np.float32), high=RELATIVE_HIGH.astype(np.float32), dtype=np.float32
        )
        self._agent_pos: np.ndarray | None = None

    def reset(self, **kwargs):
        observation, info = self.env.reset(**kwargs)
        self._agent_pos = np.array(observation["agent_pos"], dtype=np.float64)
        return observation, info

    def step(self, action):
        observation, reward, terminated, truncated, info = self.env.step(self.action(action))
        self._agent_pos = np.array(observation["agent_pos"], dtype=np.float64)
        return observation, reward, terminated, truncated, info

    def _measured(self) -> tuple[np.ndarray, np.ndarray]:
        if self._agent_pos is None:
            raise RuntimeError("Reset the env before stepping it.")
        return measured_jaw(self._agent_pos)

    def action(self, action) -> np.ndarray:
        """The absolute target (10,) float64 of the relative ``action``."""
        return target_from_relative(*self._measured(), action)

    def relative(self, absolute: np.ndarray) -> np.ndarray:
        """The action (10,) float32 that asks for the absolute target ``absolute`` from the measured pose."""
        return relative_action(*self._measured(), absolute).astype(np.float32)
