"""The extract subtask's scripted part, one throw at a time: the regrasp servo, then (opt-in) the pull.

:class:`ScriptedExtract` sequences :class:`~lerobot_suture.sim.regrasp_servo.RegraspServo` and
:class:`~lerobot_suture.sim.pull_servo.PullServo` on what the robot measures. The regrasp servo acts from the first
step until the jaw holds the tip. With ``pull`` the pull then starts from the next measured pose and turns the
needle out; without it, or once the turn is over, :meth:`ScriptedExtract.act` returns None and a learned policy
acts. A jaw that held the tip and then reads empty (its encoder fully closed: the needle slipped out) starts a new
regrasp, whatever came after the hold. The suture chain (``--scripted_regrasp``, ``--scripted_pull``) and
``benchmarks/scripted_extract.py`` both run it.
"""

from __future__ import annotations

import numpy as np

from lerobot_suture.sim.pull_servo import PullServo, PullServoConfig
from lerobot_suture.sim.regrasp_servo import RegraspServo, RegraspServoConfig
from lerobot_suture.sim.subtasks import JAW_INDEX


class ScriptedExtract:
    """One throw's scripted extract (module docstring).

    Args:
        pull: script the pull too, not only the regrasp.
        regrasp: the regrasp servo's config (its ``holding_below`` also tells an empty jaw).
        pulling: the pull's config.
    """

    def __init__(
        self, pull: bool, regrasp: RegraspServoConfig | None = None, pulling: PullServoConfig | None = None
    ):
        self.scripts_pull = pull
        self.regrasp_config = regrasp or RegraspServoConfig()
        self.pull_config = pulling or PullServoConfig()
        self.servo = RegraspServo(self.regrasp_config)
        self.pull: PullServo | None = None
        self.regrasps = 1
        """Regrasp servos started so far (1 + the times the needle slipped out after a hold)."""
        self._earlier_closings = 0  # of the regrasp servos before the current one
        self.handed_back = False
        """Whether the last :meth:`act` was the scripted part's last action: a policy acts from the next step on."""

    @property
    def closings(self) -> int:
        """Closings of the jaw so far, over every regrasp servo."""
        return self._earlier_closings + self.servo.closings

    @property
    def pulling(self) -> bool:
        """Whether a scripted pull is under way (it goes on whatever subtask the high level reads)."""
        return self.pull is not None and not self.pull.done

    def act(self, agent_pos: np.ndarray, regrasp_target: np.ndarray) -> np.ndarray | None:
        """This step's target (10,) float32 from the measured pose ``agent_pos`` (10,) and the planned regrasp
        ``regrasp_target`` (9,), or None where the learned policy acts (the regrasp, and the pull if scripted, are
        over)."""
        empty = agent_pos[JAW_INDEX] >= self.regrasp_config.holding_below
        if self.servo.held and empty:  # the needle slipped out of the jaw: take the tip again
            self._earlier_closings += self.servo.closings
            self.servo, self.pull, self.regrasps = RegraspServo(self.regrasp_config), None, self.regrasps + 1
        if self.servo.done and self.servo.held and self.scripts_pull and self.pull is None:
            self.pull = PullServo(agent_pos, self.pull_config)
        if self.pulling:
            action = self.pull.act()
            self.handed_back = self.pull.done
            return action
        if self.servo.done:
            self.handed_back = False
            return None
        action = self.servo.act(agent_pos, regrasp_target)
        self.handed_back = self.servo.done and not (self.scripts_pull and self.servo.held)
        return action
