"""Expert needle-insertion datasets in LeRobot's format: record, split, inspect, push.

- :mod:`~lerobot_suture.datasets.record`: ``lerobot-suture record`` (``record``, ``regenerate_episode``);
  its flags in :mod:`~lerobot_suture.datasets.record_config` (``RecordConfig``), the frames' layout in
  :mod:`~lerobot_suture.datasets.features`, one expert episode in :mod:`~lerobot_suture.datasets.expert_episode`,
  starting or resuming a root in :mod:`~lerobot_suture.datasets.resume`, Ctrl-C and kill in
  :mod:`~lerobot_suture.datasets.stop_signals`.
- :mod:`~lerobot_suture.datasets.split`: the train/validation split and the episodes' seeds
  (``train_episodes``, ``validation_episodes``, ``validation_seeds``); no LeRobot import.
- :mod:`~lerobot_suture.datasets.card`: the dataset card from ``recipes/card_template.md``.
- :mod:`~lerobot_suture.datasets.hub`: ``push_dataset`` and ``lerobot-suture push``.
- :mod:`~lerobot_suture.datasets.metadata`: ``meta/suture_episodes.json`` and the recording checkpoint.
- :mod:`~lerobot_suture.datasets.segment`: ``lerobot-suture segment``, one subtask of recorded running sutures,
  each segment an episode.
- :mod:`~lerobot_suture.datasets.merge`: LeRobot's ``merge_datasets`` with the run labels' NaN kept (``merge_runs``).
"""

from lerobot_suture.datasets.split import (
    episode_seeds,
    split_episodes,
    train_episodes,
    validation_episodes,
    validation_seeds,
)

__all__ = ["episode_seeds", "split_episodes", "train_episodes", "validation_episodes", "validation_seeds"]
