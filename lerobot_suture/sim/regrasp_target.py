"""The planned regrasp as an observation (opt-in, ``regrasp_target=True``): where the jaw must go to take the
needle near its tip, in the jaw's own frame.

A system with the registered wound (the current throw's entry and exit marks, and the tissue surface they lie
on) and the needle's geometry knows the arc a throw on its marks leaves the needle on; only how far the tip
protrudes is unknown, and a grasp planned at the middle of that range lands on the wire either way
(:func:`lerobot_suture.sim.extraction.planned_regrasp`). The needle's pose is never read: the plan comes from
the registration, as the robot path's ``--robot.registration`` reports the marks.

A policy must place the regrasp within about 0.5 mm and 1 degree (``studies/benchmarks/extraction_failures.py``).
Given as the motion from the jaw's measured pose to the planned
grasp, in the jaw frame (the frame of ``relative_actions``), the reach is the action the observation names. It is
seen from the observation's own ``agent_pos``, so the two agree whatever else the simulator has computed since.

:class:`RegraspTarget` appends it to ``environment_state`` (after the marks and the subtask when the env gives
them): the position change (3, m) and the first two columns of the rotation change (6), the names of
:data:`REGRASP_TARGET_NAMES`. The physics, the images and ``agent_pos`` are unchanged.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from lerobot_suture.sim.extraction import planned_regrasp
from lerobot_suture.sim.geometry import pose_vector
from lerobot_suture.sim.relative_actions import measured_jaw, relative_action
from lerobot_suture.sim.subtasks import SUBTASK_DIM
from lerobot_suture.sim.wound_marks import MARKS_DIM

STATE_KEY = "environment_state"
REGRASP_TARGET_DIM = 9
REGRASP_TARGET_NAMES = tuple(
    f"regrasp_{name}" for name in ("dx", "dy", "dz", "dr11", "dr21", "dr31", "dr12", "dr22", "dr32")
)
"""The planned regrasp's components in the jaw frame (m, then the rotation change's first two columns)."""
REGISTERED_SIZES = (0, MARKS_DIM, SUBTASK_DIM, MARKS_DIM + SUBTASK_DIM)
"""Sizes of an ``environment_state`` it may follow: none, the marks, the subtask, both."""


def regrasp_target(
    jaw_pos: np.ndarray,
    jaw_rot: np.ndarray,
    entry_point: np.ndarray,
    exit_point: np.ndarray,
    surface_normal: np.ndarray,
) -> np.ndarray:
    """(9,) float32: the planned regrasp of the throw through ``entry_point``, ``exit_point`` (m) on the surface
    of normal ``surface_normal``, seen from the jaw at ``jaw_pos`` (3,) m, ``jaw_rot`` (3, 3)."""
    target = pose_vector(*planned_regrasp(entry_point, exit_point, surface_normal), 0.0)
    return relative_action(jaw_pos, jaw_rot, target)[:REGRASP_TARGET_DIM].astype(np.float32)


def env_regrasp_target(env, agent_pos: np.ndarray) -> np.ndarray:
    """(9,) float32: :func:`regrasp_target` seen from the measured pose ``agent_pos`` (the observation's, (10,))
    with ``env``'s current throw's marks."""
    base = env.unwrapped
    return regrasp_target(
        *measured_jaw(agent_pos), base.entry_point, base.exit_point, base.phantom_rotation[:, 2]
    )


class RegraspTarget(gym.ObservationWrapper):
    """``env``'s observation plus the planned regrasp (module docstring), appended to ``environment_state``.

    Raises:
        ValueError: ``environment_state`` holds the privileged state (an ``obs_type`` with ``state``).
    """

    def __init__(self, env: gym.Env):
        spaces_ = dict(env.observation_space.spaces)
        before = spaces_.get(STATE_KEY)
        self._before = 0 if before is None else int(np.prod(before.shape))
        if self._before not in REGISTERED_SIZES:
            raise ValueError(
                "`regrasp_target` adds the planned regrasp to environment_state, which holds the privileged "
                f"state with obs_type={env.unwrapped.obs_type!r}. Pass obs_type='pixels_agent_pos'."
            )
        super().__init__(env)
        spaces_[STATE_KEY] = spaces.Box(
            -np.inf, np.inf, (self._before + REGRASP_TARGET_DIM,), dtype=np.float32
        )
        self.observation_space = spaces.Dict(spaces_)

    def observation(self, observation: dict) -> dict:
        # From the observation's own pose, not the simulator's kinematics: rendering the endoscope brings
        # those a physics step past ``agent_pos``, and a policy reads the two as one measurement.
        target = env_regrasp_target(self.env, observation["agent_pos"])
        if self._before:
            target = np.concatenate([np.asarray(observation[STATE_KEY], dtype=np.float32), target])
        return {**observation, STATE_KEY: target}
