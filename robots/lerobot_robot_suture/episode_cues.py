"""LeRobot's episode phases as the simulated arm hears them.

``lerobot-record`` and ``lerobot-rollout --strategy.type=episodic`` announce their phases to the person at
the robot through ``lerobot.utils.utils.log_say``, which logs the sentence at INFO on the root logger (and
speaks it with ``--play_sounds=true``):

- ``"Recording episode N"`` before dataset episode ``N`` (``N`` = the dataset's episode count, so a
  re-recorded episode is announced with the same ``N``);
- ``"Reset the environment"`` before the reset phase (``--dataset.reset_time_s``) between two episodes.

A real arm leaves the reset to that person. The simulated arm does it itself: :class:`EpisodeCues` is a
``logging.Handler`` on the root logger that passes the two announcements to the robot, which resets its
scene (``SutureSim``). No other LeRobot message, and no other command, changes the scene.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable

RECORDING_EPISODE = re.compile(r"^Recording episode (\d+)$")
RESET_THE_ENVIRONMENT = "Reset the environment"

logger = logging.getLogger(__name__)


class EpisodeCues(logging.Handler):
    """Calls ``on_episode(N)`` at "Recording episode N" and ``on_reset()`` at "Reset the environment".

    An exception raised by a callback is kept in :attr:`error` (logging would print and drop it); the robot
    raises it at its next call.
    """

    def __init__(self, on_episode: Callable[[int], None], on_reset: Callable[[], None]):
        super().__init__(level=logging.INFO)
        self.on_episode = on_episode
        self.on_reset = on_reset
        self.error: BaseException | None = None

    def emit(self, record: logging.LogRecord) -> None:
        try:
            message = record.getMessage()
        except Exception:  # a malformed record of someone else's: not a cue
            return
        try:
            match = RECORDING_EPISODE.match(message)
            if match:
                self.on_episode(int(match.group(1)))
            elif message == RESET_THE_ENVIRONMENT:
                self.on_reset()
        except Exception as error:  # noqa: BLE001 - handed to the robot's next call
            self.error = error

    def attach(self) -> None:
        root = logging.getLogger()
        root.addHandler(self)
        if not root.isEnabledFor(logging.INFO):
            logger.warning(
                "The root logger drops INFO messages, so the simulated arm cannot hear LeRobot's episode "
                "announcements and will not reset its scene between episodes. LeRobot's commands log at INFO."
            )

    def detach(self) -> None:
        logging.getLogger().removeHandler(self)

    def raise_pending(self) -> None:
        """Raise (once) the exception a callback raised, if any."""
        error, self.error = self.error, None
        if error is not None:
            raise RuntimeError("The simulated arm failed to reset its scene between episodes.") from error
