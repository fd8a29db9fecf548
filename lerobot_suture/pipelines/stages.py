"""The stages the pipelines share: a dataset recipe recorded, and a trained ensemble's gate calibrated;
and the file their wall times are kept in.

Each is resumable: a recording continues where it stopped, and a policy that already holds its
calibration is left as it is.
"""

from __future__ import annotations

import json
import logging
import subprocess
import time
from pathlib import Path

import draccus

logger = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[2]
CALIBRATE_CONFIG = REPO_ROOT / "policies" / "presets" / "reference_calibrate.yaml"
"""The reference's gate calibration (validation seeds, log-normal model, per-episode threshold)."""


def code_commit() -> str | None:
    """The commit of the lerobot_suture package this process imported (None outside a git checkout):
    results carry it so a figure can be traced to the code that made it."""
    result = subprocess.run(
        ["git", "-C", str(Path(__file__).parent), "rev-parse", "HEAD"], capture_output=True, text=True
    )
    return result.stdout.strip() or None


class StageTimings:
    """Wall time per stage (s), summed over invocations, written to ``path`` after every stage (an
    interrupted run keeps the time of the stages it finished)."""

    def __init__(self, path: Path):
        self.path = path
        self.seconds: dict[str, float] = json.loads(path.read_text()) if path.is_file() else {}

    def add(self, stage: str, seconds: float) -> None:
        self.seconds[stage] = round(self.seconds.get(stage, 0.0) + seconds, 1)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.path.write_text(json.dumps(self.seconds, separators=(",", ":")))

    def timed(self, stage: str, fn, *args):
        """``fn(*args)``, its wall time added to ``stage``."""
        start = time.perf_counter()
        result = fn(*args)
        self.add(stage, time.perf_counter() - start)
        return result


def record_recipe(recipe: Path, root: Path, toy: bool) -> Path:
    """``recipe`` (a ``lerobot-suture record`` YAML) recorded into ``root``; 4 episodes with ``toy``."""
    from lerobot_suture.datasets.record import record
    from lerobot_suture.datasets.record_config import parse_config

    args = [f"--config_path={recipe}", f"--root={root}", f"--resume={str(root.exists()).lower()}"]
    if toy:
        args += ["--num_episodes=4", "--checkpoint_every=2"]
    record(parse_config(args))
    return root


def calibrate_policy(policy_dir: Path, dataset_root: Path, device: str, toy: bool) -> Path:
    """The gate of the ensemble in ``policy_dir`` calibrated by :data:`CALIBRATE_CONFIG` on the validation
    seeds of ``dataset_root``; returns the calibration file (kept when already there)."""
    from lerobot_suture.runtime.calibration import CalibrateConfig, run_calibration
    from lerobot_suture.safety.ood.calibration_file import CALIBRATION_FILENAME

    calibration_file = policy_dir / CALIBRATION_FILENAME
    if calibration_file.is_file():  # written atomically once fitted; a newly trained checkpoint has none
        logger.info("already calibrated: %s", calibration_file)
        return calibration_file
    args = [f"--policy.path={policy_dir}", f"--dataset_root={dataset_root}", f"--device={device}"]
    if toy:
        args += [
            "--calibration_episodes=2",
            "--holdout_episodes=1",
            "--mode=per_prediction",
            "--batch_envs=2",
        ]
    run_calibration(draccus.parse(CalibrateConfig, config_path=CALIBRATE_CONFIG, args=args))
    return calibration_file
