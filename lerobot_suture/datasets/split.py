"""Train/validation split of a recorded dataset, and the seeds behind its episodes.

The split rule is LeRobot's own (``lerobot.datasets.factory.make_train_eval_datasets``): the last
``ceil(num_episodes * val_fraction)`` episodes are the validation episodes, the rest train. So a
dataset recorded with ``--val_fraction=f`` trains on exactly its train episodes with either of

    lerobot-train ... --dataset.eval_split=f                # LeRobot holds the same episodes out
    lerobot-train ... --dataset.episodes='[0,1,...,98]'     # the list from ``train_episodes(root)``

Episodes are i.i.d. (one fresh seed each), so the tail is as random a validation set as any. The
split is also written to ``meta/info.json`` (``"splits": {"train": "0:99", "val": "99:133"}``, LeRobot's
``"start:end"`` notation) and, as episode lists, to the episode log.

The validation episodes serve the OOD calibration later: :func:`validation_seeds` gives the env
seeds that regenerate them, :func:`validation_episodes` the episode indices to load.
"""

from __future__ import annotations

import math
from pathlib import Path

from lerobot_suture.datasets.metadata import read_episode_log

TRAIN = "train"
VAL = "val"


def split_episodes(num_episodes: int, val_fraction: float) -> tuple[list[int], list[int]]:
    """Split episode indices ``0..num_episodes-1`` into (train, val) by LeRobot's ``eval_split`` rule.

    Args:
        num_episodes: number of episodes in the dataset (>= 0).
        val_fraction: fraction held out for validation, in [0, 1).

    Returns:
        ``(train, val)``: the first ``num_episodes - ceil(num_episodes * val_fraction)`` indices and
        the rest.

    Raises:
        ValueError: ``val_fraction`` outside [0, 1), or a split that holds out every episode (LeRobot's
            ``make_train_eval_datasets`` refuses one that leaves no training episode).
    """
    if num_episodes < 0:
        raise ValueError(f"`num_episodes` must be >= 0. Got {num_episodes}.")
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"`val_fraction` must be in [0, 1). Got {val_fraction}.")
    n_val = math.ceil(num_episodes * val_fraction)
    n_train = num_episodes - n_val
    if num_episodes and not n_train:
        raise ValueError(
            f"`val_fraction`={val_fraction} holds out all {num_episodes} episode(s) and leaves none to train "
            "on (LeRobot's --dataset.eval_split refuses that too): record more episodes, or lower "
            "`val_fraction` (0 keeps every episode for training)."
        )
    return list(range(n_train)), list(range(n_train, num_episodes))


def info_splits(train: list[int], val: list[int]) -> dict[str, str]:
    """The split in ``meta/info.json``'s ``"start:end"`` notation (both parts are contiguous)."""
    splits = {TRAIN: f"0:{len(train)}"}
    if val:
        splits[VAL] = f"{len(train)}:{len(train) + len(val)}"
    return splits


def train_episodes(root: str | Path) -> list[int]:
    """Episode indices of the training split of the dataset at ``root``."""
    return list(read_episode_log(root)["splits"][TRAIN])


def validation_episodes(root: str | Path) -> list[int]:
    """Episode indices of the validation split of the dataset at ``root``."""
    return list(read_episode_log(root)["splits"][VAL])


def episode_seeds(root: str | Path) -> list[int]:
    """The env seed of every episode: ``episode_seeds(root)[i]`` regenerates episode ``i``."""
    return [int(ep["seed"]) for ep in read_episode_log(root)["episodes"]]


def validation_seeds(root: str | Path) -> list[int]:
    """Env seeds of the validation episodes, in episode order (for OOD calibration).

    ``env.reset(seed=s)`` with the recorded ``env_kwargs`` (see the episode log) puts the phantom,
    grasp and arm exactly where they were when the validation episode was recorded.

    Args:
        root: the dataset's root directory.
    """
    seeds = episode_seeds(root)
    return [seeds[i] for i in validation_episodes(root)]
