"""Training with the real ``lerobot-train`` command, resumable: the one way the demo and the reproduction
train a policy."""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

from lerobot_suture.datasets.scheduling import ordinary_scheduling

logger = logging.getLogger(__name__)


def checkpoint_step(checkpoint: Path) -> int:
    """The training step a ``lerobot-train`` checkpoint directory was saved at."""
    return int(json.loads((checkpoint / "training_state" / "training_step.json").read_text())["step"])


def run_lerobot_train(out: Path, fresh_args: list[str], steps: int, common_args: list[str]) -> Path:
    """Train into ``out`` for ``steps`` steps with ``lerobot-train``; returns the pretrained directory.

    A run interrupted earlier resumes from its last checkpoint (``--resume=true`` with the config it saved);
    a finished one is kept as it is. ``fresh_args`` start a new run; ``common_args`` (dataset root, video
    backend, save frequency) go to both.
    """
    # lerobot-train points `last` at a checkpoint only once it is completely written.
    last = out / "checkpoints" / "last"
    policy_dir = last / "pretrained_model"
    resume = last.is_dir()
    if resume and checkpoint_step(last) >= steps:
        logger.info("already trained: %s", policy_dir)
        return policy_dir
    if out.exists() and not resume:
        # Interrupted before its first checkpoint: only logs are there, and lerobot-train refuses an
        # existing output_dir unless it resumes.
        shutil.rmtree(out)
    lerobot_train = str(Path(sys.executable).parent / "lerobot-train")
    common = [*common_args, f"--steps={steps}", f"--output_dir={out}"]
    if resume:
        logger.info("resuming training from step %d: %s", checkpoint_step(last), out)
        command = [
            lerobot_train,
            f"--config_path={policy_dir / 'train_config.json'}",
            "--resume=true",
            *common,
        ]
    else:
        command = [lerobot_train, *fresh_args, *common]
    logger.info("training: %s", " ".join(command))
    subprocess.run(
        command, check=True, env={**os.environ, "HF_HUB_OFFLINE": "1"}, preexec_fn=ordinary_scheduling
    )
    return policy_dir
