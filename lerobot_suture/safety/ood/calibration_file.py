"""The gate's calibration files in a pretrained policy directory: the ensemble's ``ood_calibration.json``
(:class:`~lerobot_suture.safety.ood.calibration.OODCalibration`) and STAC's ``stac_calibration.json``
(:class:`StacCalibration`), for any other chunking policy."""

import json
import math
import os
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

from lerobot_suture.safety.ood.calibration import CALIBRATE_HINT, CalibrationMode, OODCalibration

__all__ = [
    "CALIBRATION_FILENAME",
    "CALIBRATION_REPORT_FILENAME",
    "calibration_report_file",
    "STAC_CALIBRATION_FILE",
    "CalibrationNotFoundError",
    "StacCalibration",
    "load_calibration",
    "save_calibration",
]

CALIBRATION_FILENAME = "ood_calibration.json"
"""Name of the calibration file inside a pretrained policy directory."""
CALIBRATION_REPORT_FILENAME = "ood_calibration_report.json"
"""What ``lerobot-suture calibrate`` measured, beside the calibration file."""


def calibration_report_file(calibration_file: str) -> str:
    """The report's name beside a calibration file: ``<stem>_report.json`` (``ood_calibration_report.json``)."""
    return f"{Path(calibration_file).stem}_report.json"


STAC_CALIBRATION_FILE = "stac_calibration.json"
"""STAC's calibration file inside a pretrained policy directory."""


class CalibrationNotFoundError(FileNotFoundError):
    """No calibration file in a policy directory; the message says how to create one."""


@dataclass(frozen=True)
class StacCalibration:
    """A STAC gate's calibration: the split-conformal quantile of nominal episodes' maximum STAC scores.

    Args:
        threshold: per-episode threshold on the running maximum of the score (squared MMD, >= 0).
        bandwidth: the kernel's per-dimension bandwidth (normalized action units, > 0).
        alpha: the per-episode false-alarm rate it was fitted for, in (0, 0.5).
        episodes: nominal episodes it was fitted on.
        policy_type: the policy's type (``act``, ``diffusion``, ...), for the error when another loads it.
        n_action_steps: executed steps per chunk when fitted: the shift between successive chunks.
    """

    threshold: float
    bandwidth: float = 0.5
    alpha: float = 0.05
    episodes: int = 0
    policy_type: str = ""
    n_action_steps: int = 1

    def __post_init__(self):
        if not (math.isfinite(self.threshold) and self.threshold >= 0):
            raise ValueError(f"`threshold` must be a finite number >= 0. Got {self.threshold!r}.")
        if not self.bandwidth > 0:
            raise ValueError(f"`bandwidth` must be > 0. Got {self.bandwidth!r}.")
        if not 0 < self.alpha < 0.5:
            raise ValueError(f"`alpha` must be in (0, 0.5). Got {self.alpha!r}.")

    @property
    def mode(self) -> str:
        """The gate tests the episode's running maximum (:class:`~lerobot_suture.safety.ood.gate.OODGate`)."""
        return CalibrationMode.PER_EPISODE.value

    def save(self, directory: str | os.PathLike) -> Path:
        path = Path(directory) / STAC_CALIBRATION_FILE
        path.write_text(json.dumps(asdict(self), indent=2) + "\n")
        return path

    @classmethod
    def load(cls, directory: str | os.PathLike) -> "StacCalibration":
        """Read ``directory/stac_calibration.json``.

        Raises:
            CalibrationNotFoundError: it is missing; the message says how to make it.
        """
        path = Path(directory) / STAC_CALIBRATION_FILE
        if not path.is_file():
            raise CalibrationNotFoundError(
                f"No STAC calibration at {path}. Fit one on nominal rollouts of this policy: "
                f"`lerobot-suture calibrate-stac --policy.path={directory}`."
            )
        return cls(**json.loads(path.read_text()))


def save_calibration(
    calibration: OODCalibration, directory: str | os.PathLike, filename: str = CALIBRATION_FILENAME
) -> Path:
    """Write ``calibration`` to ``directory / filename`` (created if needed, written atomically).

    Args:
        calibration: The calibration to save.
        directory: Directory, typically the pretrained policy directory.
        filename: File name inside ``directory`` (the policy's ``ood.calibration_file``).

    Returns:
        Path of the written file.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / filename
    text = json.dumps(calibration.to_dict(), indent=2, allow_nan=False) + "\n"
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=f".{filename}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def load_calibration(directory: str | os.PathLike, filename: str = CALIBRATION_FILENAME) -> OODCalibration:
    """Read the calibration saved by :func:`save_calibration` in ``directory``.

    Args:
        directory: Directory holding ``filename`` (typically the pretrained policy directory).
        filename: File name inside ``directory`` (the policy's ``ood.calibration_file``).

    Returns:
        The validated calibration.

    Raises:
        CalibrationNotFoundError: If the file does not exist (a FileNotFoundError; the message says how to
            calibrate).
        ValueError: If the file is not valid JSON, misses a key, has an unknown key, an invalid value or a
            different format ``version``; the message names the key.
    """
    path = Path(directory) / filename
    if not path.is_file():
        raise CalibrationNotFoundError(f"No OOD calibration at {path}. {CALIBRATE_HINT}")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise ValueError(
            f"OOD calibration {path} is not valid JSON ({e}). Re-run `lerobot-suture calibrate "
            "--policy.path=DIR`."
        ) from e
    try:
        return OODCalibration.from_dict(data)
    except (TypeError, ValueError) as e:
        raise ValueError(f"Invalid OOD calibration {path}: {e}") from e
