"""The O.O.D. calibration's JSON file in a pretrained policy directory: save and load."""

import json
import os
import tempfile
from pathlib import Path

from lerobot_suture.safety.ood.calibration import CALIBRATE_HINT, OODCalibration

__all__ = [
    "CALIBRATION_FILENAME",
    "CALIBRATION_REPORT_FILENAME",
    "CalibrationNotFoundError",
    "load_calibration",
    "save_calibration",
]

CALIBRATION_FILENAME = "ood_calibration.json"
"""Name of the calibration file inside a pretrained policy directory."""
CALIBRATION_REPORT_FILENAME = "ood_calibration_report.json"
"""What ``lerobot-suture calibrate`` measured, beside the calibration file."""


class CalibrationNotFoundError(FileNotFoundError):
    """No calibration file in a policy directory; the message says how to create one."""


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
