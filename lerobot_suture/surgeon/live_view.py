"""The live view of a surgeon run, in rerun: the endoscope image, the uncertainty trace, who is in control.

Rerun because it is LeRobot's own viewer (``lerobot-dataset-viz``, ``lerobot-record --display_data``) and
already installed with the ``viz`` extra; it plots a scalar trace beside an image with no GUI code here,
runs in its own process so the control loop is not slowed by drawing, and the same calls write an
``.rrd`` file headless, which a test reads back. The MuJoCo viewer shows the scene but not a trace;
OpenCV windows would need the drawing written by hand.
"""

from __future__ import annotations

import math
from pathlib import Path

from lerobot_suture.surgeon.takeover import Actor


class LiveView:
    """Logs each control step to a rerun recording: a spawned viewer, or a saved ``.rrd`` file.

    Args:
        save_path: write the recording to this ``.rrd`` file (open it later with ``rerun FILE``); None
            spawns the rerun viewer (needs a display).
    """

    def __init__(self, save_path: str | Path | None = None):
        import rerun as rr

        self.rr = rr
        self.recording = rr.RecordingStream("lerobot_suture_surgeon")
        if save_path is not None:
            self.recording.save(str(save_path))
        else:
            self.recording.spawn()

    def log(self, step: int, observation: dict, score: float, threshold: float, actor: Actor) -> None:
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
        self.recording.flush()
