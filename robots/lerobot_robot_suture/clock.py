"""The simulated arm's clock: a control step in real time, or as fast as it computes."""

from __future__ import annotations

import time

from lerobot.utils.robot_utils import precise_sleep


class ControlClock:
    """Spaces control steps at least ``period`` seconds apart in wall time when ``realtime``.

    The simulation advances one control period per step. In real time, :meth:`tick` (called just before a
    step) waits until one period has passed since the previous step began, so that simulated time never
    runs ahead of the wall clock; a caller that is slower is not made to catch up. Otherwise it returns at
    once.
    """

    def __init__(self, period: float, realtime: bool):
        if not period > 0:
            raise ValueError(f"`period` must be > 0. Got {period}.")
        self.period = float(period)
        self.realtime = bool(realtime)
        self._due = 0.0

    def tick(self) -> None:
        now = time.perf_counter()
        if self.realtime and now < self._due:
            precise_sleep(self._due - now)
            now = max(now, self._due)
        self._due = now + self.period

    def restart(self) -> None:
        """The next step runs at once (a new scene)."""
        self._due = 0.0
