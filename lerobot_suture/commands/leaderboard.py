"""``lerobot-suture leaderboard``: LeRobot's ACT and diffusion and the ensemble on every task, fifty
episodes a cell (:mod:`lerobot_suture.leaderboard.pipeline` says what runs); ``--policy.path=DIR`` adds a
user's checkpoint to the board; ``--tune=true`` tunes each family first (:mod:`lerobot_suture.leaderboard.tuning`)."""

from __future__ import annotations

import draccus

from lerobot_suture.leaderboard.pipeline import LeaderboardConfig
from lerobot_suture.leaderboard.run import run_leaderboard
from lerobot_suture.leaderboard.tuning import run_tuning


def main(argv: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=LeaderboardConfig, args=argv, exit_on_error=False)
    if cfg.tune:
        run_tuning(cfg)
        print((cfg.results_dir / "tuning.md").read_text())
        print(f"tuning.json, tuning.md and the chosen presets (presets/) in {cfg.results_dir}.")
        return
    run_leaderboard(cfg)
    print((cfg.results_dir / "leaderboard.md").read_text())
    print(f"leaderboard.json, leaderboard.md and leaderboard.png in {cfg.results_dir}.")
