"""Recording a video dataset leaves the process at the scheduling priority it had."""

from __future__ import annotations

import os

import pytest

from lerobot_suture.datasets.record import record
from lerobot_suture.datasets.record_config import RecordConfig
from lerobot_suture.datasets.scheduling import normal_scheduling

pytestmark = pytest.mark.skipif(not hasattr(os, "sched_getscheduler"), reason="Linux scheduling API")


def test_normal_scheduling_puts_the_thread_back():
    before = os.sched_getscheduler(0)
    with normal_scheduling():
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))  # as a library might, unasked
        assert os.sched_getscheduler(0) == os.SCHED_BATCH
    assert os.sched_getscheduler(0) == before


def test_recording_a_video_dataset_keeps_the_priority(tmp_path):
    # Run as root, LeRobot's SVT-AV1 encoder raises the encoding thread to SCHED_FIFO 99 and leaves it there.
    before = os.sched_getscheduler(0), os.sched_getparam(0)
    record(
        RecordConfig(
            repo_id="suture-tests/sched",
            root=str(tmp_path / "d"),
            num_episodes=1,
            val_fraction=0.0,
            image_size=32,
            video=True,
        )
    )
    assert (os.sched_getscheduler(0), os.sched_getparam(0)) == before


def test_the_training_child_starts_at_ordinary_priority_whatever_the_parent_was_left_at():
    import subprocess
    import sys

    from lerobot_suture.datasets.scheduling import ordinary_scheduling

    before = os.sched_getscheduler(0), os.sched_getparam(0)
    os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))  # as an encoder might leave the parent
    try:
        out = subprocess.run(
            [sys.executable, "-c", "import os; print(os.sched_getscheduler(0))"],
            check=True,
            capture_output=True,
            text=True,
            preexec_fn=ordinary_scheduling,
        )
    finally:
        os.sched_setscheduler(0, *before)
    assert int(out.stdout) == os.SCHED_OTHER
