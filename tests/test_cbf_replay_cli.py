"""`lerobot-suture cbf-replay`: the paper's experiment 4 from the command line."""

import json

import numpy as np
from PIL import Image

from lerobot_suture.cli import main


def test_cbf_replay_writes_the_figure_and_keeps_the_safe_trajectory_inside(tmp_path):
    main(["cbf-replay", f"--output_dir={tmp_path}", "--seed=1", "--pull_steps=8"])
    metrics = json.loads((tmp_path / "cbf_replay.json").read_text())
    assert metrics["left_set_reference"] and not metrics["left_set_safe"]
    assert metrics["h_min_safe"] >= 0.0 > metrics["h_min_reference"]
    image = np.asarray(Image.open(tmp_path / "cbf_replay.png").convert("L"), dtype=float)
    assert image.shape[1] > 3 * 300 and image.std() > 10, "figure missing or blank"
