"""The live view of a surgeon run, in rerun: the endoscope image, the uncertainty trace, who is in control.

Rerun because it is LeRobot's own viewer (``lerobot-dataset-viz``, ``lerobot-record --display_data``) and
already installed with the ``viz`` extra; it plots a scalar trace beside an image with no GUI code here,
runs in its own process so the control loop is not slowed by drawing, and the same calls write an
``.rrd`` file headless, which a test reads back. The MuJoCo viewer shows the scene but not a trace;
OpenCV windows would need the drawing written by hand.
"""

from __future__ import annotations

import logging
import math
import os
import sys
from pathlib import Path

from lerobot_suture.runtime.takeover import Actor

logger = logging.getLogger(__name__)

VIEWER_FLUSH_TIMEOUT_S = 5.0
"""How long closing waits for a spawned viewer to take the last steps; a viewer that has gone away (or
never came up) would otherwise hold the run's end forever."""


def display_available() -> bool:
    """Whether a window can open: on Linux an X or Wayland display must be named; elsewhere assume so."""
    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


class LiveView:
    """Logs each control step to a rerun recording: a spawned viewer, or a saved ``.rrd`` file.

    Args:
        save_path: write the recording to this ``.rrd`` file (open it later with ``rerun FILE``); None
            spawns the rerun viewer (needs a display).

    Without a display, or when the viewer cannot start, the view says so in one warning and is off
    (``enabled`` false: ``log`` and ``close`` do nothing); the run it watches carries on.
    """

    def __init__(self, save_path: str | Path | None = None):
        import rerun as rr

        self.rr = rr
        self.recording = None
        self.spawned = save_path is None
        if self.spawned and not display_available():
            logger.warning(
                "live view off: no display (DISPLAY and WAYLAND_DISPLAY are unset); pass "
                "--view_path=FILE.rrd to save it and open it later with `rerun FILE.rrd`"
            )
            return
        recording = rr.RecordingStream("lerobot_suture_surgeon")
        try:
            if save_path is not None:
                recording.save(str(save_path))
            else:
                recording.spawn()
        except Exception as exc:  # a viewer that cannot start must not end the run it would show
            logger.warning("live view off: the rerun viewer could not start (%s)", " ".join(str(exc).split()))
            return
        self.recording = recording

    @property
    def enabled(self) -> bool:
        return self.recording is not None

    def log(self, step: int, observation: dict, score: float, threshold: float, actor: Actor) -> None:
        if self.recording is None:
            return
        rr, rec = self.rr, self.recording
        rec.set_time("step", sequence=step)
        if "pixels" in observation:
            rec.log("endoscope", rr.Image(observation["pixels"]["endoscope"]))
        if math.isfinite(score):
            rec.log("uncertainty/score", rr.Scalars(score))
        if math.isfinite(threshold):
            rec.log("uncertainty/threshold", rr.Scalars(threshold))
        rec.log("control/actor", rr.Scalars(float(int(actor))))
        rec.log("control/who", rr.TextLog(f"step {step}: {actor.name.lower()} in control"))

    def close(self) -> None:
        if self.recording is None:
            return
        if self.spawned:
            self.recording.flush(timeout_sec=VIEWER_FLUSH_TIMEOUT_S)
        else:
            self.recording.flush()  # a file: every logged step is written before the run ends
