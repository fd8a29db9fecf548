"""Ctrl-C and ``kill`` during a recording: SIGINT / SIGTERM become :class:`RecordingInterrupted`, held
back while an episode is being saved so that it is never cut in half."""

from __future__ import annotations

import contextlib
import logging
import signal
import threading

# What a recording reports goes to one logger, the recorder's.
logger = logging.getLogger("lerobot_suture.datasets.record")


class RecordingInterrupted(KeyboardInterrupt):
    """Ctrl-C or ``kill`` (SIGINT / SIGTERM) stopped a recording; finished episodes were kept."""

    def __init__(self, signum: int):
        super().__init__(f"recording stopped by {signal.Signals(signum).name}")
        self.signum = signum

    @property
    def exit_status(self) -> int:
        """The shell's convention for a process ended by a signal: 128 + its number (130 for Ctrl-C)."""
        return 128 + self.signum


class StopSignals:
    """Turns SIGINT/SIGTERM into :class:`RecordingInterrupted`, held back while a critical section runs.

    Saving an episode (add_frame ... save_episode ... checkpoint) must not be cut in half; a signal
    that arrives during it is raised as soon as it ends. Once ``stopping`` is set (cleanup), further
    signals are only logged.
    """

    _SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self._previous: dict[int, object] = {}
        self._depth = 0
        self._pending: int | None = None
        self.stopping = False

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for sig in self._SIGNALS:
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc):
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()
        return False

    def _handle(self, signum, frame):
        if self.stopping:
            logger.warning(
                "%s received: already stopping, finishing the dataset.", signal.Signals(signum).name
            )
            return
        if self._depth > 0:
            self._pending = signum
            return
        raise RecordingInterrupted(signum)

    @contextlib.contextmanager
    def deferred(self):
        self._depth += 1
        try:
            yield
        finally:
            self._depth -= 1
        if self._depth == 0 and self._pending is not None and not self.stopping:
            signum, self._pending = self._pending, None
            raise RecordingInterrupted(signum)
