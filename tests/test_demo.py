"""`lerobot-suture demo`, the main job, at its smallest: interrupted mid-training, then resumed to the end."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from lerobot_suture.cli import main as cli_main

TRAIN_STEPS = 30
SMALL = [
    "--scenarios=[nominal]",
    "--episodes_per_scenario=1",
    "--frames_per_strip=2",
    "--frame_size=32",
    "--dataset_episodes=2",
    f"--train_steps={TRAIN_STEPS}",
    "--checkpoint_every=5",
]


def _assert_picture(path: Path) -> None:
    """A PNG that shows something: not one flat colour."""
    image = np.asarray(Image.open(path).convert("L"), dtype=float)
    assert image.std() > 5, f"{path} is blank"


def _step(checkpoint: Path) -> int:
    return json.loads((checkpoint / "training_state" / "training_step.json").read_text())["step"]


def _stats(directory: Path) -> dict[str, tuple[int, int]]:
    """(inode, mtime) of every file: a file written again, even with the same bytes, shows."""
    return {
        p.relative_to(directory).as_posix(): (p.stat().st_ino, p.stat().st_mtime_ns)
        for p in directory.rglob("*")
        if p.is_file()
    }


def _ctrl_c_as_at_a_terminal() -> None:
    """In the demo's process, before it starts: SIGINT's default action. A shell without job control
    starts background jobs with SIGINT ignored (``cmd &`` in a script), every child inherits that, and
    Python then installs no KeyboardInterrupt handler: the interrupt would never arrive."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.slow  # multi-process or training: make test-slow
def test_an_interrupted_demo_resumes_and_keeps_what_it_finished(tmp_path, capsys):
    out = tmp_path / "demo"
    last = out / "train" / "checkpoints" / "last"
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    log = tmp_path / "interrupted.log"  # a file, not a pipe: a full pipe would stall the demo
    # Ctrl-C reaches the whole foreground process group: the demo and its lerobot-train.
    with log.open("wb") as stderr:
        proc = subprocess.Popen(
            [str(Path(sys.executable).parent / "lerobot-suture"), "demo", f"--output_dir={out}", *SMALL],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=stderr,
            start_new_session=True,
            preexec_fn=_ctrl_c_as_at_a_terminal,
        )
    deadline = time.monotonic() + 300
    try:
        while not last.is_dir() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert last.is_dir(), f"no checkpoint within the deadline: {log.read_text()[-3000:]}"
        assert proc.poll() is None, "the demo finished before it could be interrupted"
        os.killpg(proc.pid, signal.SIGINT)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, log.read_text()[-3000:]
    assert log.read_text().rstrip().endswith("lerobot-suture demo: interrupted.")
    assert not (out / "summary.json").exists()
    interrupted_at = _step(last)
    assert 5 <= interrupted_at < TRAIN_STEPS
    finished = last.resolve()
    kept = _stats(finished)

    cli_main(["demo", f"--output_dir={out}", *SMALL])

    # Training went on from the interrupted run's last checkpoint, which was neither deleted nor redone.
    assert _stats(finished) == kept
    assert _step(last) == TRAIN_STEPS
    summary = json.loads((out / "summary.json").read_text())
    assert summary["policy"] == str(last / "pretrained_model")
    assert summary["dataset"]["episodes"] == 2
    assert (summary["dataset"]["train_episodes"], summary["dataset"]["val_episodes"]) == ([0], [1])
    _assert_picture(Path(summary["scenarios"]["nominal"]["strip"]))
    assert summary["scenarios"]["nominal"]["success_rate"] == 1.0
    assert (last / "pretrained_model" / "ood_calibration.json").is_file()
    experiments = Path(summary["experiments"]["dir"])
    metrics = json.loads((experiments / "metrics.json").read_text())
    assert set(metrics["experiments"]) == {"1", "2", "3.1", "3.2"}
    assert len(summary["experiments"]["figures"]) == 5
    for figure in summary["experiments"]["figures"]:
        _assert_picture(Path(figure))
    assert "## Out of distribution" in (experiments / "report.md").read_text()
    printed = capsys.readouterr().out
    assert f"summary: {out / 'summary.json'}" in printed

    # Run again when everything is done: nothing is trained, calibrated or run again.
    done = _stats(out / "train") | {f"experiments/{k}": v for k, v in _stats(experiments).items()}
    cli_main(["demo", f"--output_dir={out}", *SMALL])
    assert done == _stats(out / "train") | {f"experiments/{k}": v for k, v in _stats(experiments).items()}
