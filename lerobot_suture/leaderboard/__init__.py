"""The leaderboard (``lerobot-suture leaderboard``): every policy on every task, the same test seeds for all.

- :mod:`~lerobot_suture.leaderboard.cells`: a cell (one policy, one task, one condition) and its summary;
- :mod:`~lerobot_suture.leaderboard.board`: the board as a table and a figure;
- :mod:`~lerobot_suture.leaderboard.pipeline`: the run's config and its stages (record, train, calibrate,
  evaluate each cell);
- :mod:`~lerobot_suture.leaderboard.run`: one run as a graph of those stages, the further training seeds
  included, and the board it writes;
- :mod:`~lerobot_suture.leaderboard.tuning`: each family's configurations scored on validation seeds;
- :mod:`~lerobot_suture.leaderboard.ray_stages`: those stages as Ray tasks, on this machine or a cluster;
- :mod:`~lerobot_suture.leaderboard.schedule`: the graph's time on N machines, projected from stage times.
"""
