"""``lerobot-suture demo``: the main job at a small default, writing what a person looks at.

Steps, each writing under ``output_dir`` (default ``outputs/demo/``):

1. the scripted expert in every scenario: an endoscope-view strip (PNG) per scenario;
2. a small expert dataset (``dataset/``), recorded by the same code as ``lerobot-suture record``;
3. ``summary.json`` with every figure above.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import draccus
import numpy as np
from tqdm import tqdm

from lerobot_suture.rollout_expert import run_expert_episode
from lerobot_suture.sim.scenarios import SCENARIOS

logger = logging.getLogger(__name__)


@dataclass
class DemoConfig:
    """Args:
    output_dir: where the strips and ``summary.json`` go.
    scenarios: scenarios to run (default: all).
    seed: seed of the first episode; each scenario runs ``episodes_per_scenario`` seeds from it.
    episodes_per_scenario: expert episodes per scenario (the first one is drawn as a strip).
    frames_per_strip: endoscope frames per strip.
    frame_size: side of each frame (px).
    dataset_episodes: expert episodes in the demo dataset (0 skips recording).
    """

    output_dir: Path = Path("outputs/demo")
    scenarios: list[str] = field(default_factory=lambda: list(SCENARIOS))
    seed: int = 0
    episodes_per_scenario: int = 3
    frames_per_strip: int = 6
    frame_size: int = 160
    dataset_episodes: int = 12

    def __post_init__(self):
        unknown = [s for s in self.scenarios if s not in SCENARIOS]
        if unknown:
            raise ValueError(f"`scenarios` must be drawn from {SCENARIOS}. Got unknown {unknown}.")
        if self.episodes_per_scenario < 1 or self.frames_per_strip < 2:
            raise ValueError(
                "`episodes_per_scenario` must be >= 1 and `frames_per_strip` >= 2. "
                f"Got {self.episodes_per_scenario}, {self.frames_per_strip}."
            )


def save_strip(frames: list[np.ndarray], path: Path) -> None:
    """Frames side by side, as one PNG."""
    from PIL import Image

    Image.fromarray(np.concatenate(frames, axis=1)).save(path)


def record_demo_dataset(cfg: DemoConfig) -> dict:
    """Record (or finish recording) the demo's expert dataset; a rerun adds nothing."""
    from lerobot_suture.datasets.record import RecordConfig, record

    root = cfg.output_dir / "dataset"
    result = record(
        RecordConfig(
            repo_id="local/suture_demo",
            root=str(root),
            num_episodes=cfg.dataset_episodes,
            seed=cfg.seed,
            resume=root.exists(),
        )
    )
    return {
        "repo_id": result.repo_id,
        "root": str(result.root),
        "episodes": result.num_episodes,
        "frames": result.num_frames,
        "train_episodes": result.train_episodes,
        "val_episodes": result.val_episodes,
        "discarded": result.discarded,
    }


def run_demo(cfg: DemoConfig) -> dict:
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    summary: dict = {"scenarios": {}}
    jobs = [(s, cfg.seed + k) for s in cfg.scenarios for k in range(cfg.episodes_per_scenario)]
    for scenario, seed in tqdm(jobs, desc="expert episodes", unit="episode"):
        first = seed == cfg.seed
        episode = run_expert_episode(
            seed, scenario, n_frames=cfg.frames_per_strip if first else 0, frame_size=cfg.frame_size
        )
        entry = summary["scenarios"].setdefault(scenario, {"episodes": []})
        entry["episodes"].append(episode.summary())
        if first:
            strip = cfg.output_dir / f"expert_{scenario}.png"
            save_strip(episode.frames, strip)
            entry["strip"] = str(strip)
    for entry in summary["scenarios"].values():
        entry["success_rate"] = float(np.mean([e["success"] for e in entry["episodes"]]))
    if cfg.dataset_episodes:
        summary["dataset"] = record_demo_dataset(cfg)
    path = cfg.output_dir / "summary.json"
    path.write_text(json.dumps(summary, indent=2))
    summary["path"] = str(path)
    return summary


def main(argv: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=DemoConfig, args=argv)
    summary = run_demo(cfg)
    for name, entry in summary["scenarios"].items():
        print(f"{name:32s} expert success {entry['success_rate']:.2f}  strip: {entry['strip']}")
    if "dataset" in summary:
        d = summary["dataset"]
        print(f"dataset {d['repo_id']}: {d['episodes']} episodes, {d['frames']} frames at {d['root']}")
    print(f"summary: {summary['path']}")
