"""The running suture's high level: which subtask the arm is in, from what the robot measures.

A throw of a running suture is four subtasks in a fixed order, the scripted expert's stages:

=========== ================================================= ===========================================
subtask     what the arm does                                 ends when (measured)
=========== ================================================= ===========================================
insert      drives the held needle in at the entry mark and    the jaw opens (it lets go of the needle);
            out at the exit mark                              with the wound's marks, only within
                                                              ``release_radius`` of the entry mark:
                                                              elsewhere the needle was lost (``pick_up``,
                                                              the same throw)
extract     reaches the protruding tip, closes on it and       the jaw has travelled ``pulled_out_travel``
            pulls the needle out along its arc                  since it closed on the tip
lay_down    carries the needle to the phantom and lets go      the jaw opens
pick_up     grasps the needle again, ready for the next throw  the jaw closes on the needle: the next
                                                              throw's insert
=========== ================================================= ===========================================

The rules read the measured pose alone (``observation.state``: the jaw tip's position and the jaw's closure), never
the simulator's contact flags or the needle's pose: the jaw closure is an encoder reading and the travel comes from
the arm's kinematics, so a real arm has both. Rules rather than a learned classifier: the order of the subtasks is
fixed, and each boundary but one is a jaw event that a threshold on one encoder reads without error; the one that
is not (the end of the pull) is a distance. A jaw closed on the needle is told from one closed on nothing by the
same encoder: the wire between its faces stops it short (0.80-0.88 of its travel in all 72,081 closed frames of the
running-suture recipe's 133 sutures), where an empty jaw closes fully (1); the rules judge a closing once the jaw
has stopped (:data:`STOPPED_CHANGE`), since one closing on nothing passes through the wire's readings on its way.
So a closing beside the needle neither starts the pull's travel nor ends a pick-up, and the stage goes on. A
learned classifier would need labelled rollouts of every policy it serves and could misfire where the rules
cannot. The order is also their limit: a jaw
event the plan does not have (the needle dropped and grasped again) would read as the next subtask. Given the
registered wound's marks (the current throw's entry and exit points, as the ``marks`` observation and the robot
path's registration give them), the rules tell a release at the wound from a needle lost on the way. The throw
counts up when a laid-down needle is let go (the next throw's pick-up). ``benchmarks/subtask_rules.py`` measures
how often the rules agree with the expert's own stage, nominal and under the scenarios.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from lerobot_suture.checks import check_positive
from lerobot_suture.sim.wound_marks import MARKS_DIM

SUBTASKS = ("insert", "extract", "lay_down", "pick_up")
"""A throw's subtasks in their order; ``pick_up`` leads into the next throw's ``insert``."""
JAW_INDEX = 9
"""Index of the jaw's closure (0 open, 1 closed) in the measured pose."""
STOPPED_CHANGE = 0.01
"""Change of the jaw's closure over a control step below which a closing jaw has stopped. A jaw is judged to hold
the needle only once it has stopped: one closing on nothing passes through the wire's readings on its way to fully
closed."""
SUBTASK_KEY = "environment_state"
SUBTASK_DIM = len(SUBTASKS) + 1
SUBTASK_NAMES = tuple(f"subtask_{name}" for name in SUBTASKS) + ("throw",)
"""The subtask as an observation: one-hot over :data:`SUBTASKS`, then the throw (0-based)."""


@dataclass(frozen=True)
class SubtaskRulesConfig:
    """Args:
    closed_above: jaw closure (0 open, 1 closed) above which the jaw counts as closed, in (0, 1).
    holding_below: jaw closure below which a closed jaw holds the needle (its wire stops the jaw), above
        ``closed_above``; a jaw closed on nothing reads above it. Over 1: every closed jaw holds it.
    pulled_out_travel: distance (m) the jaw travels after closing on the needle's tip beyond which the needle
        is out of the tissue, > 0 (the default sits just short of the scripted expert's pull).
    release_radius: with the wound's marks, the distance (m) from the entry mark within which the jaw lets go
        of the needle at the end of an insert, > 0 (the default leaves room around where the expert lets go).
    """

    closed_above: float = 0.5
    pulled_out_travel: float = 0.019
    release_radius: float = 0.010
    holding_below: float = 0.95

    def __post_init__(self):
        if not 0.0 < self.closed_above < 1.0:
            raise ValueError(f"`closed_above` must be in (0, 1). Got {self.closed_above!r}.")
        if not self.holding_below > self.closed_above:  # NaN fails too
            raise ValueError(
                f"`holding_below` must be above `closed_above` ({self.closed_above}). Got {self.holding_below!r}."
            )
        check_positive(self, ("pulled_out_travel", "release_radius"), unit="m")


class SubtaskRules:
    """The high level of one suture at a time: :meth:`reset` with the episode's first measured pose, then
    :meth:`update` with each control step's measured pose (and the wound's marks, when registered); both return
    ``(subtask, throw)`` for that step.

    Args:
        config: the thresholds (:class:`SubtaskRulesConfig`).
    """

    def __init__(self, config: SubtaskRulesConfig | None = None):
        self.config = config or SubtaskRulesConfig()
        self.subtask, self.throw = SUBTASKS[0], 0
        self._closed = self._holding = True
        self._closure: float | None = None
        self._tip_grasped_at: np.ndarray | None = None

    def reset(self, pose: np.ndarray) -> tuple[str, int]:
        """A new suture: with the needle held it starts at ``insert``, from a needle on the phantom at ``pick_up``."""
        self._closed = self._is_closed(pose)
        self._holding = self._closed and self._holds(pose)  # the jaw at rest at the start
        self._closure = float(pose[JAW_INDEX])
        self.subtask, self.throw = ("insert" if self._holding else "pick_up"), 0
        self._tip_grasped_at = None
        return self.subtask, self.throw

    def update(self, pose: np.ndarray, marks: np.ndarray | None = None) -> tuple[str, int]:
        """The subtask and the throw (0-based) at the control step whose measured pose is ``pose``, (10,);
        ``marks``: the current throw's entry and exit points (6,) m, or None without a registered wound."""
        closed = self._is_closed(pose)
        closure = float(pose[JAW_INDEX])
        stopped = self._closure is not None and abs(closure - self._closure) < STOPPED_CHANGE
        # A hold starts once the closing jaw has stopped short of closed, and lasts while the jaw stays so.
        holding = closed and self._holds(pose) and (self._holding or stopped)
        opened, grasped = self._closed and not closed, holding and not self._holding
        self._closed, self._holding, self._closure = closed, holding, closure
        position = np.asarray(pose[:3], dtype=np.float64)
        if self.subtask == "insert" and opened:
            at_wound = (
                marks is None
                or np.linalg.norm(position - np.asarray(marks)[:3]) <= self.config.release_radius
            )
            self.subtask = "extract" if at_wound else "pick_up"  # elsewhere: the needle was lost
        elif self.subtask == "extract":
            if grasped:
                self._tip_grasped_at = position
            elif not holding:  # let go, or closed beside the needle: no pull under way
                self._tip_grasped_at = None
            elif self._tip_grasped_at is not None:
                if np.linalg.norm(position - self._tip_grasped_at) >= self.config.pulled_out_travel:
                    self.subtask, self._tip_grasped_at = "lay_down", None
        elif self.subtask == "lay_down" and opened:
            self.subtask, self.throw = "pick_up", self.throw + 1  # the throw is over: the next one's pick-up
        elif self.subtask == "pick_up" and grasped:
            self.subtask = "insert"
        return self.subtask, self.throw

    def _is_closed(self, pose: np.ndarray) -> bool:
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (10,) or not np.all(np.isfinite(pose)):
            raise ValueError(f"`pose` must be the (10,) finite measured pose. Got shape {pose.shape}.")
        return bool(pose[JAW_INDEX] > self.config.closed_above)

    def _holds(self, pose: np.ndarray) -> bool:
        return bool(pose[JAW_INDEX] < self.config.holding_below)


def subtask_vector(subtask: str, throw: int) -> np.ndarray:
    """(5,) float32: ``subtask`` one-hot over :data:`SUBTASKS`, then ``throw``."""
    vector = np.zeros(SUBTASK_DIM, dtype=np.float32)
    vector[SUBTASKS.index(subtask)] = 1.0
    vector[-1] = float(throw)
    return vector


def subtask_reading(vector) -> tuple[str, int]:
    """The ``(subtask, throw)`` that :func:`subtask_vector` made ``vector`` (5,) from.

    Raises:
        ValueError: ``vector`` is not one subtask's one-hot followed by a whole throw >= 0.
    """
    vector = np.asarray(vector, dtype=np.float64).reshape(-1)
    one_hot, throw = vector[: len(SUBTASKS)], vector[-1] if vector.size else math.nan
    if (
        vector.shape != (SUBTASK_DIM,)
        or not np.all(np.isin(one_hot, (0.0, 1.0)))
        or one_hot.sum() != 1.0
        or not (throw >= 0 and float(throw).is_integer())
    ):
        raise ValueError(
            f"A subtask reading is a one-hot over {SUBTASKS} and then the throw (a whole number >= 0). Got {vector}."
        )
    return SUBTASKS[int(np.argmax(one_hot))], int(throw)


class SubtaskObservation(gym.Wrapper):
    """``env``'s observation plus the high level's subtask and throw (:func:`subtask_vector`), appended to
    ``environment_state``: after the wound's marks when the env gives them (11,), else alone (5,). The rules read
    each step's measured pose (and the marks), as a policy conditioned on the subtask would receive it from the
    high level; the physics, the images and ``agent_pos`` are unchanged.

    Raises:
        ValueError: ``environment_state`` holds something other than the marks (the privileged ``obs_type``\\ s).
    """

    def __init__(self, env: gym.Env, config: SubtaskRulesConfig | None = None):
        super().__init__(env)
        spaces_ = dict(env.observation_space.spaces)
        before = spaces_.get(SUBTASK_KEY)
        self._marks = before is not None
        if before is not None and before.shape != (MARKS_DIM,):
            raise ValueError(
                "`subtask` adds the subtask to environment_state, which holds the privileged state with obs_type="
                f"{env.unwrapped.obs_type!r}. Pass obs_type='pixels_agent_pos' (the wound's marks may stay)."
            )
        size = SUBTASK_DIM + (MARKS_DIM if self._marks else 0)
        spaces_[SUBTASK_KEY] = spaces.Box(-np.inf, np.inf, (size,), dtype=np.float32)
        self.observation_space = spaces.Dict(spaces_)
        self.rules = SubtaskRules(config)

    def reset(self, **kwargs):
        observation, info = self.env.reset(**kwargs)
        return self._with(observation, self.rules.reset(observation["agent_pos"])), info

    def step(self, action):
        observation, reward, terminated, truncated, info = self.env.step(action)
        marks = observation[SUBTASK_KEY] if self._marks else None
        return (
            self._with(observation, self.rules.update(observation["agent_pos"], marks)),
            reward,
            terminated,
            truncated,
            info,
        )

    def _with(self, observation: dict, reading: tuple[str, int]) -> dict:
        vector = subtask_vector(*reading)
        if self._marks:
            vector = np.concatenate([np.asarray(observation[SUBTASK_KEY], dtype=np.float32), vector])
        return {**observation, SUBTASK_KEY: vector}
