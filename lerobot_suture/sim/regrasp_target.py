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

Where the plan comes from (``regrasp_from``, :data:`REGRASP_SOURCES`):

- ``"marks"`` (the default): the arc through the registered marks, as above. It is exact for a throw on that
  arc, which is where every extraction episode starts; a learned insert leaves the needle within the marks'
  2 mm tolerance but off that arc, and the plan then lies beside the wire.
- ``"release"``: the needle as the jaw let go of it (:func:`released_regrasp`). The arm's kinematics give the
  jaw's pose at the last control step of the insert (the high level's rules, :mod:`~lerobot_suture.sim.subtasks`,
  on the measured pose), and the grasp model (the needle's nominal place in the jaw, ``task.GRASP_ANGLE``) puts
  the needle there: the throw as it was made, not as it was planned. Its error is the grasp's own
  (``task.GRASP_RANGES``: up to about 1.5 mm at the regrasp in the narrow range), not the throw's.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from lerobot_suture.sim.extraction import REGRASP_ANGLE, planned_regrasp
from lerobot_suture.sim.geometry import grasp_transform, jaw_holding, needle_in_world, pose_vector
from lerobot_suture.sim.relative_actions import measured_jaw, relative_action
from lerobot_suture.sim.subtasks import JAW_INDEX, SUBTASK_DIM, SubtaskRules
from lerobot_suture.sim.task import GRASP_ANGLE
from lerobot_suture.sim.wound_marks import MARKS_DIM

STATE_KEY = "environment_state"
REGRASP_TARGET_DIM = 9
REGRASP_TARGET_NAMES = tuple(
    f"regrasp_{name}" for name in ("dx", "dy", "dz", "dr11", "dr21", "dr31", "dr12", "dr22", "dr32")
)
"""The planned regrasp's components in the jaw frame (m, then the rotation change's first two columns)."""
REGISTERED_SIZES = (0, MARKS_DIM, SUBTASK_DIM, MARKS_DIM + SUBTASK_DIM)
"""Sizes of an ``environment_state`` it may follow: none, the marks, the subtask, both."""
REGRASP_SOURCES = ("marks", "release")
"""Where the planned regrasp comes from (module docstring)."""


def check_regrasp_source(source: str, planned: bool, fix: str) -> None:
    """Refuse a ``regrasp_from`` that is none of :data:`REGRASP_SOURCES`, or one other than ``"marks"`` when no plan
    is asked for (``planned`` False); ``fix`` is how the caller's user asks for it (``--env.regrasp_target=true``).

    Raises:
        ValueError: naming the sources, or ``fix``.
    """
    if source not in REGRASP_SOURCES:
        raise ValueError(f"`regrasp_from` must be one of {REGRASP_SOURCES}. Got {source!r}.")
    if source != "marks" and not planned:
        raise ValueError(
            f"`regrasp_from={source}` says where the planned regrasp comes from, and no plan is asked for: pass "
            f"{fix} too."
        )


def released_regrasp(release_pos: np.ndarray, release_rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The jaw pose (position (3,) m, rotation (3, 3), world) that grasps near its tip the needle a jaw at
    ``release_pos`` (3,) m, ``release_rot`` (3, 3) let go of, the needle held with the nominal grasp."""
    needle = needle_in_world(release_pos, release_rot, *grasp_transform(GRASP_ANGLE, 0.0, 0.0))
    return jaw_holding(*needle, *grasp_transform(REGRASP_ANGLE, 0.0, 0.0))


def released_regrasp_target(jaw_pos, jaw_rot, release_pos, release_rot) -> np.ndarray:
    """(9,) float32: :func:`released_regrasp` of the release pose ``release_pos``, ``release_rot``, seen from the
    jaw at ``jaw_pos`` (3,) m, ``jaw_rot`` (3, 3)."""
    target = pose_vector(*released_regrasp(release_pos, release_rot), 0.0)
    return relative_action(jaw_pos, jaw_rot, target)[:REGRASP_TARGET_DIM].astype(np.float32)


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


class RegraspTarget(gym.Wrapper):
    """``env``'s observation plus the planned regrasp (module docstring), appended to ``environment_state``.

    Args:
        env: the env.
        source: where the plan comes from, one of :data:`REGRASP_SOURCES`.

    Raises:
        ValueError: ``environment_state`` holds the privileged state (an ``obs_type`` with ``state``), or
            ``source`` is none of :data:`REGRASP_SOURCES`.
    """

    def __init__(self, env: gym.Env, source: str = "marks"):
        check_regrasp_source(source, True, "regrasp_target=True")
        self.source = source
        self._rules = SubtaskRules()
        self._release: tuple[np.ndarray, np.ndarray] | None = None
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

    def reset(self, **kwargs):
        observation, info = self.env.reset(**kwargs)
        self._rules.reset(observation["agent_pos"])
        self._release = measured_jaw(observation["agent_pos"])
        return self._observation(observation), info

    def step(self, action):
        observation, reward, terminated, truncated, info = self.env.step(action)
        if self.source == "release":
            self._track_release(observation)
        return self._observation(observation), reward, terminated, truncated, info

    def _observation(self, observation: dict) -> dict:
        # From the observation's own pose, not the simulator's kinematics: rendering the endoscope brings
        # those a physics step past ``agent_pos``, and a policy reads the two as one measurement.
        pose = observation["agent_pos"]
        if self.source == "marks":
            target = env_regrasp_target(self.env, pose)
        else:
            target = released_regrasp_target(*measured_jaw(pose), *self._release)
        if self._before:
            target = np.concatenate([np.asarray(observation[STATE_KEY], dtype=np.float32), target])
        return {**observation, STATE_KEY: target}

    def _track_release(self, observation: dict) -> None:
        """Keep the jaw's measured pose while it holds the needle in an insert (the high level's rules read the
        subtask, with the marks where the env gives them first): after the insert, where it let go."""
        pose = observation["agent_pos"]
        marks = (
            observation[STATE_KEY][:MARKS_DIM]
            if self._before in (MARKS_DIM, MARKS_DIM + SUBTASK_DIM)
            else None
        )
        subtask, _ = self._rules.update(pose, marks)
        if subtask == "insert" and pose[JAW_INDEX] > self._rules.config.closed_above:
            self._release = measured_jaw(pose)
