"""The stages the pipelines share: a dataset recipe recorded, and a trained ensemble's gate calibrated.

Each is resumable: a recording continues where it stopped, and a policy that already holds its
calibration is left as it is.
"""

from __future__ import annotations

import logging
from pathlib import Path

import draccus

logger = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[2]
CALIBRATE_CONFIG = REPO_ROOT / "policies" / "presets" / "reference_calibrate.yaml"
"""The reference's gate calibration (validation seeds, log-normal model, per-episode threshold)."""


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
