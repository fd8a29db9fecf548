"""The demonstrations' training split with the run labels, merged with every round's new frames (LeRobot's
own dataset tools), with the policy's normalization kept.

Fine-tuning with ``lerobot-train --policy.path=DIR`` normalizes with the statistics of the dataset it is
given (it passes ``dataset.meta.stats`` to the policy's saved pre- and post-processors). New data would shift
them, and the ensemble's actions, its covariance in dataset units and the gate's calibrated threshold would
lose their meaning. So the merged dataset's ``meta/stats.json`` carries, for every feature the policy
normalizes, the statistics saved in the policy's preprocessor (those of the original demonstrations); the
other features keep the merged statistics.

The merge is :func:`~lerobot_suture.datasets.merge.merge_runs` (LeRobot's ``merge_datasets``, with the run
labels' NaN scores kept NaN).

Each dataset is built in a ``.partial`` sibling and renamed when complete, so a killed run leaves either
nothing or a finished dataset.
"""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

logger = logging.getLogger(__name__)

PREPROCESSOR_FILE = "policy_preprocessor.json"


def _partial(out: Path) -> Path:
    partial = out.with_name(out.name + ".partial")
    if partial.exists():
        shutil.rmtree(partial)
    partial.mkdir(parents=True)
    return partial


def load_dataset(root: Path, repo_id: str):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_suture.datasets.video import resolve_video_backend

    return LeRobotDataset(repo_id, root=root, video_backend=resolve_video_backend())


def training_demonstrations(dataset_root: Path, repo_id: str, out: Path) -> Path:
    """The demonstrations at ``dataset_root`` without their validation episodes (LeRobot's
    ``delete_episodes``), labelled as surgeon demonstrations (``label_demonstrations``), at ``out``."""
    from lerobot.datasets.dataset_tools import delete_episodes

    from lerobot_suture.datasets.split import validation_episodes
    from lerobot_suture.surgeon.record_run import label_demonstrations

    partial = _partial(out)
    demos = load_dataset(Path(dataset_root), repo_id)
    validation = validation_episodes(dataset_root)
    if validation:
        demos = delete_episodes(demos, validation, output_dir=partial / "train", repo_id=f"{repo_id}_train")
    label_demonstrations(demos, partial / "labelled", f"{repo_id}_labelled")
    os.replace(partial / "labelled", out)
    shutil.rmtree(partial)
    return out


def policy_normalizer_stats(policy_dir: Path) -> dict:
    """The statistics of the normalizer step saved in the policy's preprocessor: feature -> stat -> array."""
    from lerobot.processor import PolicyProcessorPipeline

    if not (Path(policy_dir) / PREPROCESSOR_FILE).is_file():
        raise FileNotFoundError(
            f"No {PREPROCESSOR_FILE} in {policy_dir}: pass a policy saved by lerobot-train, whose "
            "preprocessor holds the normalization statistics."
        )
    pipeline = PolicyProcessorPipeline.from_pretrained(policy_dir, config_filename=PREPROCESSOR_FILE)
    for step in pipeline.steps:
        stats = getattr(step, "stats", None)
        if stats:
            return {key: {name: _numpy(value) for name, value in s.items()} for key, s in stats.items()}
    raise ValueError(f"The preprocessor in {policy_dir} has no normalizer statistics to keep.")


def _numpy(value):
    import numpy as np

    return value.detach().cpu().numpy() if hasattr(value, "detach") else np.asarray(value)


def keep_normalization(root: Path, stats: dict) -> None:
    """Overwrite ``root``'s statistics of the features in ``stats`` with them (LeRobot's stats file)."""
    from lerobot.datasets.io_utils import load_stats, write_stats

    merged = load_stats(root) or {}
    for key, feature_stats in stats.items():
        merged[key] = {**merged.get(key, {}), **feature_stats}
    write_stats(merged, root)


def aggregate(
    demonstrations: Path,
    new_roots: list[Path],
    out: Path,
    repo_id: str,
    normalizer_stats: dict,
    repeats: int = 1,
) -> Path:
    """The labelled demonstrations and the new datasets, each ``repeats`` times, merged (LeRobot's
    ``merge_datasets``) at ``out``, with ``normalizer_stats`` kept (see the module docstring)."""
    if repeats < 1:
        raise ValueError(f"`repeats` must be >= 1. Got {repeats}.")
    from lerobot_suture.datasets.merge import merge_runs

    partial = _partial(out)
    sources = [load_dataset(demonstrations, "local/demonstrations")]
    new = [load_dataset(root, f"local/{root.parent.name}_{root.name}") for root in new_roots]
    sources += new * repeats
    merge_runs(sources, repo_id, partial / "merged")
    keep_normalization(partial / "merged", normalizer_stats)
    os.replace(partial / "merged", out)
    shutil.rmtree(partial)
    return out
