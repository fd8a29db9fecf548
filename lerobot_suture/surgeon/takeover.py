"""Who is in control of the arm at each control step: the policy, the surgeon, or nobody (the arm holds).

Transitions, evaluated once per control step before anyone acts:

=========== ======================================== ===========================================
from        event                                    to
=========== ======================================== ===========================================
policy      the surgeon takes over (a key, a button) surgeon
policy      the O.O.D. gate releases control         surgeon, or hold when there is no surgeon
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

GATE_RELEASED, TAKEN_OVER, HANDED_BACK = "gate released", "taken over", "handed back"
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

    def _change(self, step: int, to: Actor, why: str) -> None:
        self.handovers.append((step, self.actor, to, why))
        self.actor = to
