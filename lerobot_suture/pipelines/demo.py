"""The main job at a small default (``lerobot-suture demo``), writing what a person looks at.

Steps, each writing under ``output_dir`` (default ``outputs/demo/``), all at toy scale:

1. the scripted expert in every scenario: an endoscope-view strip (PNG) per scenario;
2. a small expert dataset (``dataset/``), recorded by the same code as ``lerobot-suture record``;
3. a tiny ensemble trained for a few steps by the real ``lerobot-train`` (``train/``);
4. its O.O.D. gate calibrated by ``lerobot-suture calibrate``;
5. one run of each of the paper's experiments and the CBF figures, by ``lerobot-suture experiments``
   (``experiments/``: figures, ``metrics.json``, ``report.md``);
6. ``summary.json`` with where everything is.

A toy ensemble trained for a few steps does not insert the needle; the demo shows the machinery. The
README gives the commands and the reference results of a properly trained ensemble.

Interrupted (Ctrl-C, a kill), the same command picks up where it stopped: the dataset's recording
resumes, training resumes from its last checkpoint (``lerobot-train --resume=true``), a calibration
already written for the trained policy is kept, and experiments already run on that calibration are
not run again.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from lerobot_suture.runtime.expert_rollout import run_expert_episode
from lerobot_suture.runtime.training import run_lerobot_train
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
    dataset_episodes: expert episodes in the demo dataset (0 skips recording and everything after).
    train_steps: ``lerobot-train`` steps of the toy ensemble.
    checkpoint_every: ``lerobot-train`` steps between checkpoints; an interrupted demo resumes training
        from the last one.
    train: train, calibrate and run the experiments (false stops after the dataset).
    """

    output_dir: Path = Path("outputs/demo")
    scenarios: list[str] = field(default_factory=lambda: list(SCENARIOS))
    seed: int = 0
    episodes_per_scenario: int = 3
    frames_per_strip: int = 6
    frame_size: int = 160
    dataset_episodes: int = 12
    train_steps: int = 30
    checkpoint_every: int = 10
    train: bool = True

    def __post_init__(self):
        unknown = [s for s in self.scenarios if s not in SCENARIOS]
        if unknown:
            raise ValueError(f"`scenarios` must be drawn from {SCENARIOS}. Got unknown {unknown}.")
        if not self.scenarios:
            raise ValueError(f"`scenarios` must name at least one of {SCENARIOS}. Got [].")
        if self.episodes_per_scenario < 1 or self.frames_per_strip < 2:
            raise ValueError(
                "`episodes_per_scenario` must be >= 1 and `frames_per_strip` >= 2. "
                f"Got {self.episodes_per_scenario}, {self.frames_per_strip}."
            )
        if not 16 <= self.frame_size <= 640:
            raise ValueError(f"`frame_size` must be in [16, 640] px. Got {self.frame_size}.")
        if self.train_steps < 1 or self.checkpoint_every < 1:
            raise ValueError(
                "`train_steps` and `checkpoint_every` must be >= 1. "
                f"Got {self.train_steps}, {self.checkpoint_every}."
            )
        # The dataset holds out its last quarter for the calibration, and training needs the rest.
        if self.dataset_episodes < 0 or (self.train and self.dataset_episodes == 1):
            raise ValueError(
                "`dataset_episodes` must be 0 (no dataset) or >= 2 (episodes to train on and a validation "
                f"episode to calibrate on); 1 is enough only with --train=false. Got {self.dataset_episodes}."
            )


def save_strip(frames: list[np.ndarray], path: Path) -> None:
    """Frames side by side, as one PNG."""
    from PIL import Image

    Image.fromarray(np.concatenate(frames, axis=1)).save(path)


def record_demo_dataset(cfg: DemoConfig) -> dict:
    """Record (or finish recording) the demo's expert dataset; a rerun adds nothing."""
    from lerobot_suture.datasets.record import record
    from lerobot_suture.datasets.record_config import RecordConfig

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


# A toy ensemble for the demo: 2 members, 32 px images read by ResNet18's first stage only (a few MB per
# checkpoint instead of 260), a two-level U-Net, DDIM with 5 steps.
TOY_POLICY_FLAGS = [
    "--policy.type=ensemble_diffusion",
    "--policy.n_members=2",
    "--policy.vision_backbone_stages=1",
    "--policy.n_obs_steps=2",
    "--policy.horizon=8",
    "--policy.n_action_steps=4",
    "--policy.drop_n_last_frames=3",
    "--policy.resize_shape=[32,32]",
    "--policy.down_dims=[16,32]",
    "--policy.diffusion_step_embed_dim=16",
    "--policy.spatial_softmax_num_keypoints=8",
    "--policy.noise_scheduler_type=DDIM",
    "--policy.prediction_type=sample",
    "--policy.num_train_timesteps=20",
    "--policy.num_inference_steps=5",
    "--policy.pretrained_backbone_weights=null",
    "--policy.push_to_hub=false",
    "--policy.device=cpu",
]


def train_toy_ensemble(cfg: DemoConfig, dataset_root: Path) -> Path:
    """Train the toy ensemble with the real ``lerobot-train`` command; returns its pretrained directory.

    A run interrupted earlier resumes from its last checkpoint; a finished one is kept as it is.
    """
    from lerobot_suture.datasets.split import train_episodes
    from lerobot_suture.datasets.video import resolve_video_backend

    fresh = [
        *TOY_POLICY_FLAGS,
        "--dataset.repo_id=local/suture_demo",
        f"--dataset.episodes=[{','.join(str(i) for i in train_episodes(dataset_root))}]",
        "--batch_size=4",
        "--num_workers=0",
        "--log_freq=10",
        "--job_name=suture_demo",
    ]
    common = [
        f"--dataset.root={dataset_root}",
        f"--dataset.video_backend={resolve_video_backend()}",  # quietly, where torchcodec does not load
        f"--save_freq={cfg.checkpoint_every}",
    ]
    return run_lerobot_train(cfg.output_dir / "train", fresh, cfg.train_steps, common)


def calibrate_and_run_experiments(cfg: DemoConfig, policy_dir: Path) -> dict:
    """``lerobot-suture calibrate`` then ``lerobot-suture experiments`` at toy scale, each skipped when a
    run interrupted later left its result for this policy and calibration."""
    from lerobot_suture.experiments.paper import ExperimentsConfig, run_experiments
    from lerobot_suture.runtime.calibration import CalibrateConfig, run_calibration
    from lerobot_suture.runtime.config import PolicyPathConfig
    from lerobot_suture.safety.ood.calibration_file import CALIBRATION_FILENAME

    calibration_file = policy_dir / CALIBRATION_FILENAME
    if calibration_file.is_file():  # written atomically once fitted; a retrained policy has none
        logger.info("toy ensemble already calibrated: %s", calibration_file)
    else:
        run_calibration(
            CalibrateConfig(
                policy=PolicyPathConfig(path=policy_dir),
                dataset_root=cfg.output_dir / "dataset",
                calibration_episodes=3,
                holdout_episodes=1,
                mode="per_prediction",
            )
        )
    out = cfg.output_dir / "experiments"
    # metrics.json then report.md are the experiments' last writes; metrics.json names the calibration.
    metrics_file = out / "metrics.json"
    calibration = json.loads(calibration_file.read_text())
    done = metrics_file.is_file() and (out / "report.md").is_file()
    if done and json.loads(metrics_file.read_text())["calibration"] == calibration:
        logger.info("experiments already run with this calibration: %s", out)
        figures = json.loads(metrics_file.read_text())["figures"]
    else:
        result = run_experiments(
            ExperimentsConfig(
                policy=PolicyPathConfig(path=policy_dir),
                output_dir=out,
                nominal_episodes=2,
                expert_episodes=5,
                needle_drop_runs=1,
                camera_moved_runs=1,
                phantom_servo_runs=1,
                phantom_moved_after_insertion_runs=1,
                cbf_runs=1,
                enforced_runs=1,
            )
        )
        figures = result["figures"]
    return {"dir": str(out), "figures": [str(out / name) for name in figures.values()]}


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
        if cfg.train:
            policy_dir = train_toy_ensemble(cfg, Path(summary["dataset"]["root"]))
            summary["policy"] = str(policy_dir)
            summary["experiments"] = calibrate_and_run_experiments(cfg, policy_dir)
    path = cfg.output_dir / "summary.json"
    path.write_text(json.dumps(summary, indent=2))
    summary["path"] = str(path)
    return summary
