"""What lerobot-suture adds to a LeRobotDataset's ``meta/``: the episode log and the recording checkpoint.

LeRobot's ``meta/info.json`` is rewritten from a typed dataclass that drops unknown keys, so our
metadata lives in files of its own beside it, which LeRobot ignores, keeps through ``finalize``,
uploads with ``push_to_hub`` and downloads with the rest of ``meta/``:

``meta/suture_episodes.json`` (:data:`EPISODE_LOG_PATH`), the episode log:
    the seed of every kept episode (``episodes[i]["seed"]`` regenerates episode ``i``), the
    train/validation split, every discarded attempt with the reason, the environment and expert
    settings, the recording config and the command that reproduces the dataset.

``meta/suture_checkpoint.json`` (:data:`CHECKPOINT_PATH`), present only while a recording runs or
after it died without cleaning up (SIGKILL, power loss): the last durable state (episode log,
``info.json``, ``stats.json`` and the list of data files). ``--resume=true`` rolls the dataset back
to it, so a killed recording loses at most the episodes since the last checkpoint.

Only the standard library here: reading seeds and splits needs neither LeRobot nor MuJoCo.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
from pathlib import Path

EPISODE_LOG_PATH = "meta/suture_episodes.json"
CHECKPOINT_PATH = "meta/suture_checkpoint.json"
INFO_PATH = "meta/info.json"
STATS_PATH = "meta/stats.json"
FORMAT_VERSION = 1

# Files the checkpoint restores by content rather than by listing.
_RESTORED = {INFO_PATH, STATS_PATH, EPISODE_LOG_PATH, CHECKPOINT_PATH, "README.md"}


def write_json_atomic(path: Path, obj, compact: bool = False) -> None:
    """Write ``obj`` as JSON to ``path`` so a reader (or a kill) never sees half a file; ``compact``: no
    indentation (results, which ``docs/results`` keeps to a size budget), else indented (configs people read)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w") as f:
        json.dump(obj, f, **({"separators": (",", ":")} if compact else {"indent": 2}))
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def read_json(path: Path):
    with open(path) as f:
        return json.load(f)


def read_episode_log(root: str | Path) -> dict:
    """The episode log of a dataset recorded by ``lerobot-suture record``.

    Args:
        root: the dataset's root directory (the ``--root`` it was recorded to, or a Hub snapshot).

    Raises:
        FileNotFoundError: if ``root`` holds no episode log.
    """
    path = Path(root) / EPISODE_LOG_PATH
    if not path.is_file():
        raise FileNotFoundError(
            f"No episode log at {path}: {root} is not a dataset recorded by `lerobot-suture record` "
            "(or it is still being recorded). Pass the `--root` the dataset was recorded to."
        )
    return read_json(path)


def write_episode_log(root: str | Path, log: dict) -> None:
    write_json_atomic(Path(root) / EPISODE_LOG_PATH, log)


def _data_files(root: Path) -> list[str]:
    """Every file under ``root`` the checkpoint tracks by name (relative POSIX paths, sorted)."""
    files = []
    for path in root.rglob("*"):
        if path.is_file():
            rel = path.relative_to(root).as_posix()
            if rel not in _RESTORED and not path.name.startswith("."):
                files.append(rel)
    return sorted(files)


def write_checkpoint(root: str | Path, log: dict) -> None:
    """Record the dataset's current on-disk state (call it right after ``finalize``) as durable.

    Args:
        root: dataset root.
        log: the episode log matching the finalized dataset.
    """
    root = Path(root)
    stats_path = root / STATS_PATH
    write_json_atomic(
        root / CHECKPOINT_PATH,
        {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "episode_log": log,
            "info": read_json(root / INFO_PATH),
            "stats": read_json(stats_path) if stats_path.is_file() else None,
            "files": _data_files(root),
        },
    )
    write_episode_log(root, log)


def read_checkpoint(root: str | Path) -> dict | None:
    path = Path(root) / CHECKPOINT_PATH
    return read_json(path) if path.is_file() else None


def clear_checkpoint(root: str | Path) -> None:
    """Mark the dataset clean: the recording finished or stopped gracefully."""
    (Path(root) / CHECKPOINT_PATH).unlink(missing_ok=True)


def checkpoint_owner_alive(checkpoint: dict) -> bool:
    """Whether the process that wrote ``checkpoint`` still runs (on this host)."""
    if checkpoint.get("host") != socket.gethostname():
        return False
    pid = int(checkpoint.get("pid", -1))
    if pid <= 0 or pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def roll_back_to_checkpoint(root: str | Path, checkpoint: dict) -> list[str]:
    """Undo everything written after ``checkpoint``: delete newer files, restore the metadata.

    Args:
        root: dataset root.
        checkpoint: as read by :func:`read_checkpoint`.

    Returns:
        The relative paths of the files that were removed.
    """
    root = Path(root)
    keep = set(checkpoint["files"])
    removed = [rel for rel in _data_files(root) if rel not in keep]
    for rel in removed:
        (root / rel).unlink()
    # Encoder scratch directories (tempfile.mkdtemp(dir=root)) and emptied folders.
    for path in sorted(root.iterdir()):
        if path.is_dir() and path.name.startswith("tmp"):
            shutil.rmtree(path, ignore_errors=True)
    for path in (root / "meta").glob(".*.tmp"):
        path.unlink()
    for path in sorted(root.rglob("*"), key=lambda p: len(p.parts), reverse=True):
        if path.is_dir() and not any(path.iterdir()):
            path.rmdir()
    write_json_atomic(root / INFO_PATH, checkpoint["info"])
    if checkpoint["stats"] is None:
        (root / STATS_PATH).unlink(missing_ok=True)
    else:
        write_json_atomic(root / STATS_PATH, checkpoint["stats"])
    write_episode_log(root, checkpoint["episode_log"])
    return removed
