"""Who is in control of the arm at each control step: the policy, the surgeon, or nobody (the arm holds); and
the surgeons every episode loop knows without a teleoperator (nobody, and the scripted expert as a stand-in).

Transitions, evaluated once per control step before anyone acts:

=========== ======================================== ===========================================
from        event                                    to
=========== ======================================== ===========================================
policy      the surgeon takes over (a key, a button) surgeon
policy      the O.O.D. gate releases control         surgeon, or hold when there is no surgeon
policy      the tissue moves beyond what the CBF     surgeon, or hold when there is no surgeon
            was declared to cover
surgeon     the surgeon hands back (a key, a button) policy (its gate re-armed)
hold        the surgeon hands back                   policy (its gate re-armed)
=========== ======================================== ===========================================

A step acted on by the surgeon is an intervention (LeRobot's ``is_intervention``: a person's action
replaced the policy's); a hold step is not (nobody acted). Handing back re-arms the gate: the policy
starts over from the current observation with a fresh gate, and a gate that finds it still out of
distribution releases control again.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from lerobot_suture.expert import ScriptedExpert

GATE_RELEASED, TAKEN_OVER, HANDED_BACK = "gate released", "taken over", "handed back"
TISSUE_MOTION = "tissue motion"
"""Why control changed hands: the ``why`` of :attr:`Takeover.handovers`."""


class Actor(IntEnum):
    """Who acted at a step; the integer is the dataset's ``complementary_info.actor``."""

    POLICY = 0
    SURGEON = 1
    HOLD = 2


@dataclass
class Takeover:
    """The control state machine of one episode.

    Args:
        has_surgeon: whether someone takes over when the gate releases control (false: the arm holds).
    """

    has_surgeon: bool
    actor: Actor = field(default=Actor.POLICY, init=False)
    handovers: list[tuple[int, Actor, Actor, str]] = field(default_factory=list, init=False)
    """(step, from, to, why) of every change of control."""

    def reset(self) -> None:
        self.actor = Actor.POLICY
        self.handovers = []

    def update(self, step: int, *, released: bool, take_over: bool, hand_back: bool) -> Actor:
        """The actor of control step ``step`` after its events.

        Args:
            step: control step index in the episode.
            released: the policy's gate has released control (latched until the policy is reset).
            take_over: the surgeon asked for control this step.
            hand_back: the surgeon handed control back to the policy this step (wins over ``take_over``
                in the same step: a surgeon who presses both means to let go).
        """
        if self.actor is Actor.POLICY:
            if take_over and self.has_surgeon:
                self._change(step, Actor.SURGEON, TAKEN_OVER)
            elif released:
                self._change(step, Actor.SURGEON if self.has_surgeon else Actor.HOLD, GATE_RELEASED)
        elif hand_back:
            self._change(step, Actor.POLICY, HANDED_BACK)
        return self.actor

    def tissue_moved(self, step: int) -> Actor:
        """The tissue moved beyond the CBF's premise while the policy acted: from ``step`` on, the surgeon acts
        (or the arm holds)."""
        if self.actor is Actor.POLICY:
            self._change(step, Actor.SURGEON if self.has_surgeon else Actor.HOLD, TISSUE_MOTION)
        return self.actor

    def _change(self, step: int, to: Actor, why: str) -> None:
        self.handovers.append((step, self.actor, to, why))
        self.actor = to


@dataclass
class SurgeonInput:
    """What the surgeon did since the last poll.

    Args:
        teleop_action: the teleoperator's action dict (``delta_x/y/z`` in [-1, 1], ``gripper``).
        rotation: (3,) rotation command in [-1, 1] about the jaw's axes.
        take_over: asked for control.
        hand_back: handed control back to the policy.
        events: LeRobot's teleop events (``TeleopEvents`` -> bool) as the teleoperator reported them.
    """

    teleop_action: dict = field(default_factory=dict)
    rotation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    take_over: bool = False
    hand_back: bool = False
    events: dict = field(default_factory=dict)


class NoSurgeon:
    """Nobody takes over: a released arm holds its pose."""

    name = "none"
    present = False

    def poll(self) -> SurgeonInput:
        return SurgeonInput()

    def begin_episode(self, env) -> None:
        """Called once per episode, after the env's reset."""

    def intervenes(self, env, action: np.ndarray) -> bool:
        """Whether the surgeon, seeing the policy's ``action`` at the env's state, takes over before it runs
        (a person presses a key instead; only a scripted surgeon judges the action itself)."""
        return False

    def take_control(self, env, observation: dict) -> None:
        raise RuntimeError("Nobody is there to take control.")

    def act(self, env, command: SurgeonInput) -> np.ndarray:
        raise RuntimeError("Nobody is there to act.")

    def close(self) -> None:
        pass


class ExpertSurgeon(NoSurgeon):
    """The scripted expert as the surgeon: it works out where the task stands and finishes it."""

    name = "expert"
    present = True

    def __init__(self, expert: ScriptedExpert | None = None):
        self.expert = expert or ScriptedExpert()

    def take_control(self, env, observation: dict) -> None:
        self.expert.reset(env)

    def act(self, env, command: SurgeonInput) -> np.ndarray:
        return self.expert.act(env)


class SubtaskExpertSurgeon(ExpertSurgeon):
    """The scripted expert as a surgeon who takes over the running suture's subtask under way and hands control
    back once the expert has moved on to the next one (a stage gate's enforcement: that subtask, not the rest of
    the suture). The expert's own stage (privileged) tells it where one subtask ends; it acts one step of the
    next before handing back."""

    name = "expert_per_subtask"

    def __init__(self, expert: ScriptedExpert | None = None):
        super().__init__(expert)
        self._taken: str | None = None  # the stage it took over, once it has acted

    def take_control(self, env, observation: dict) -> None:
        super().take_control(env, observation)
        self._taken = None

    def act(self, env, command: SurgeonInput) -> np.ndarray:
        action = super().act(env, command)
        if self._taken is None:
            self._taken = self.expert.stage
        return action

    def poll(self) -> SurgeonInput:
        done = self._taken is not None and self.expert.stage != self._taken
        if done:
            self._taken = None
        return SurgeonInput(hand_back=done)
