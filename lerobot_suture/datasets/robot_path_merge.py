"""Merging a robot-path recording (``lerobot-rollout``, e.g. ``gated_dagger``) with the expert demonstrations.

The two hold the same keys, dtypes and shapes for the image, the state and the action, but LeRobot's
``merge_datasets`` asks for equal features and robot type, and they differ in what is around them:

- the robot path names the pose features ``x.pos`` ... (LeRobot's convention, ``docs/robot.md``), the expert
  data ``x`` ...; and its robot type is ``suture_sim``, the expert data's ``psm``;
- the expert data holds what the recorder computed from privileged state (``observation.needle_keypoints``,
  ``next.*``), the robot path LeRobot's ``intervention`` and the gate's ``ood_*`` labels.

:func:`demonstrations_in_robot_layout` copies the demonstrations into the recording's layout (LeRobot's
``modify_features``: the privileged features dropped; ``intervention`` False, ``ood_score`` and
``ood_threshold`` NaN, ``ood_decision`` False, as no policy ran; the recording's names and robot type), and
:func:`merge_with_demonstrations` merges the two with :func:`~lerobot_suture.datasets.merge.merge_runs` (which
keeps the NaN labels NaN), ready for ``lerobot-train``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from lerobot_suture.datasets.scheduling import normal_scheduling

_ROBOT_LABELS = {
    "intervention": (False, "bool"),
    "ood_score": (np.nan, "float32"),
    "ood_threshold": (np.nan, "float32"),
    "ood_decision": (False, "bool"),
}


def demonstrations_in_robot_layout(demonstrations, recording, output_dir: str | Path, repo_id: str):
    """A copy of ``demonstrations`` with the features, names and robot type of ``recording`` (both
    ``LeRobotDataset``s); returns it.

    Raises:
        ValueError: the two disagree on a key both hold (dtype or shape), or the recording has a feature the
            demonstrations lack and this module cannot fill.
    """
    from lerobot.datasets.dataset_tools import modify_features
    from lerobot.datasets.io_utils import write_info
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ours, theirs = demonstrations.meta.features, recording.meta.features
    for key in set(ours) & set(theirs):
        if ours[key]["dtype"] != theirs[key]["dtype"] or list(ours[key]["shape"]) != list(
            theirs[key]["shape"]
        ):
            raise ValueError(
                f"{key!r} differs: {ours[key]['dtype']} {ours[key]['shape']} in the demonstrations, "
                f"{theirs[key]['dtype']} {theirs[key]['shape']} in the recording; record both at one image size."
            )
    missing = [k for k in theirs if k not in ours and k not in _ROBOT_LABELS]
    if missing:
        raise ValueError(f"The recording has features {missing} the demonstrations lack; cannot fill them.")
    n = demonstrations.meta.total_frames
    add = {
        key: (np.full((n, 1), value, dtype=dtype), dict(theirs[key]))
        for key, (value, dtype) in _ROBOT_LABELS.items()
        if key in theirs and key not in ours
    }
    remove = [k for k in ours if k not in theirs]
    with normal_scheduling():  # copying the videos may start the encoder, which leaves the thread real-time
        copy = modify_features(
            demonstrations,
            add_features=add or None,
            remove_features=remove or None,
            output_dir=output_dir,
            repo_id=repo_id,
        )
    info_path = Path(output_dir) / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    for key in ("observation.state", "action"):
        info["features"][key]["names"] = theirs[key]["names"]
    info["robot_type"] = recording.meta.robot_type
    copy.meta.info.features.update({k: info["features"][k] for k in ("observation.state", "action")})
    copy.meta.info.robot_type = info["robot_type"]
    write_info(copy.meta.info, copy.meta.root)
    return LeRobotDataset(repo_id, root=output_dir)


def merge_with_demonstrations(demonstrations, recording, output_dir: str | Path, repo_id: str):
    """``demonstrations`` in the recording's layout merged with ``recording`` at ``output_dir``; returns it."""
    from lerobot_suture.datasets.merge import merge_runs

    output_dir = Path(output_dir)
    converted = demonstrations_in_robot_layout(
        demonstrations,
        recording,
        output_dir.with_name(output_dir.name + ".demonstrations"),
        repo_id + "_demonstrations",
    )
    return merge_runs([converted, recording], repo_id, output_dir)
