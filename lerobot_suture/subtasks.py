"""The running suture's high level: which subtask the arm is in, from what the robot measures.

A throw of a running suture is four subtasks in a fixed order, the scripted expert's stages:

=========== ================================================= ===========================================
subtask     what the arm does                                 ends when (measured)
=========== ================================================= ===========================================
insert      drives the held needle in at the entry mark and    the jaw opens (it lets go of the needle)
            out at the exit mark
extract     reaches the protruding tip, closes on it and       the jaw has travelled ``pulled_out_travel``
            pulls the needle out along its arc                  since it closed on the tip
lay_down    carries the needle to the phantom and lets go      the jaw opens
pick_up     grasps the needle again, ready for the next throw  the jaw closes: the next throw's insert
=========== ================================================= ===========================================

The rules read the measured pose alone (``observation.state``: the jaw tip's position and the jaw's closure),
never the simulator's contact flags or the needle's pose: the jaw closure is an encoder reading and the travel
comes from the arm's kinematics, so a real arm has both. Rules rather than a learned classifier: the order of the
subtasks is fixed, and each boundary but one is a jaw event that a threshold on one encoder reads without error;
the one that is not (the end of the pull) is a distance. A learned classifier would need labelled rollouts of
every policy it serves and could misfire where the rules cannot. The order is also their limit: a jaw event the
plan does not have (the needle dropped and grasped again) reads as the next subtask, and the rules stay out of
phase from there. ``benchmarks/subtask_rules.py`` measures how often the rules agree with the expert's own stage,
nominal and under the scenarios.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

SUBTASKS = ("insert", "extract", "lay_down", "pick_up")
"""A throw's subtasks in their order; ``pick_up`` leads into the next throw's ``insert``."""
JAW_INDEX = 9
"""Index of the jaw's closure (0 open, 1 closed) in the measured pose."""


@dataclass(frozen=True)
class SubtaskRulesConfig:
    """Args:
    closed_above: jaw closure (0 open, 1 closed) above which the jaw counts as closed, in (0, 1).
    pulled_out_travel: distance (m) the jaw travels after closing on the needle's tip beyond which the needle
        is out of the tissue, > 0 (the scripted expert pulls 19.5 mm).
    """

    closed_above: float = 0.5
    pulled_out_travel: float = 0.019

    def __post_init__(self):
        if not 0.0 < self.closed_above < 1.0:
            raise ValueError(f"`closed_above` must be in (0, 1). Got {self.closed_above!r}.")
        if not (math.isfinite(self.pulled_out_travel) and self.pulled_out_travel > 0):
            raise ValueError(
                f"`pulled_out_travel` must be a finite distance > 0 (m). Got {self.pulled_out_travel!r}."
            )


class SubtaskRules:
    """The high level of one suture at a time: :meth:`reset` with the episode's first measured pose, then
    :meth:`update` with each control step's measured pose; both return ``(subtask, throw)`` for that step.

    Args:
        config: the thresholds (:class:`SubtaskRulesConfig`).
    """

    def __init__(self, config: SubtaskRulesConfig | None = None):
        self.config = config or SubtaskRulesConfig()
        self.subtask, self.throw = SUBTASKS[0], 0
        self._closed, self._inserted = True, True
        self._tip_grasped_at: np.ndarray | None = None

    def reset(self, pose: np.ndarray) -> tuple[str, int]:
        """A new suture: with the needle held it starts at ``insert``, from a needle on the phantom at ``pick_up``."""
        self._closed = self._is_closed(pose)
        self.subtask, self.throw = ("insert" if self._closed else "pick_up"), 0
        self._inserted = self._closed
        self._tip_grasped_at = None
        return self.subtask, self.throw

    def update(self, pose: np.ndarray) -> tuple[str, int]:
        """The subtask and the throw (0-based) at the control step whose measured pose is ``pose``, (10,)."""
        closed = self._is_closed(pose)
        opened, shut = self._closed and not closed, closed and not self._closed
        self._closed = closed
        position = np.asarray(pose[:3], dtype=np.float64)
        if self.subtask == "insert" and opened:
            self.subtask = "extract"
        elif self.subtask == "extract":
            if shut:
                self._tip_grasped_at = position
            elif closed and self._tip_grasped_at is not None:
                if np.linalg.norm(position - self._tip_grasped_at) >= self.config.pulled_out_travel:
                    self.subtask, self._tip_grasped_at = "lay_down", None
        elif self.subtask == "lay_down" and opened:
            self.subtask = "pick_up"
        elif self.subtask == "pick_up" and shut:
            # A suture from a needle on the phantom: its first pick-up leads into throw 0.
            self.throw += int(self._inserted)
            self.subtask, self._inserted = "insert", True
        return self.subtask, self.throw

    def _is_closed(self, pose: np.ndarray) -> bool:
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (10,) or not np.all(np.isfinite(pose)):
            raise ValueError(f"`pose` must be the (10,) finite measured pose. Got shape {pose.shape}.")
        return bool(pose[JAW_INDEX] > self.config.closed_above)
