"""``lerobot-suture cbf-replay``: the paper's experiment 4 offline, a recorded unsafe throw filtered through
the CBF and plotted (:mod:`lerobot_suture.experiments.cbf_replay_figure`)."""

from __future__ import annotations

import json

import draccus

from lerobot_suture.experiments.cbf_replay_figure import CBFReplayConfig, run_cbf_replay


def main(argv: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=CBFReplayConfig, args=argv, exit_on_error=False)
    metrics = run_cbf_replay(cfg)
    print(json.dumps(metrics, indent=2, default=float))
