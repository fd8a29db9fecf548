"""A recipe's reference from nothing (``lerobot-suture reproduce``), and its table beside the committed one.

Four stages into ``output_dir`` (default ``outputs/reproduce/``), each with the recipe files of the
repository, each skipped when an earlier (interrupted) run finished it:

1. ``data/``: the moving-phantom expert dataset (``recipes/suture_expert_servo.yaml``);
2. ``train/``: the reference ensemble (``policies/presets/reference.json``) trained by the real
   ``lerobot-train``, resumed from its last checkpoint after an interruption;
3. the gate's calibration (``policies/presets/reference_calibrate.yaml``), written beside the policy;
4. ``experiments/``: the paper's experiments on the test seeds (``lerobot-suture experiments``).

Then ``comparison.md`` / ``comparison.json``: every headline figure of the new run beside the committed
reference's (``docs/results/prior_servo_5500/metrics.json``), marked within or outside its tolerance
(``lerobot_suture.experiments.compare``). ``timings.json`` holds each stage's wall time, summed over the
invocations that worked on it.

``--toy=true`` runs the same pipeline at toy scale (4 episodes, 4 training steps, one run per
experiment): minutes, for a smoke test; its figures are not expected to match.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

from lerobot_suture.pipelines.stages import CALIBRATE_CONFIG, StageTimings, calibrate_policy, record_recipe

logger = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[2]
REFERENCE_RESULTS = REPO_ROOT / "docs" / "results" / "prior_servo_5500"


@dataclass(frozen=True)
class Recipe:
    """The files one trained policy is made from, and the committed results a new run is compared with."""

    dataset: Path
    train_preset: Path
    results: Path


RECIPES = {
    # The paper's reference: moving-phantom demonstrations.
    "reference": Recipe(
        REPO_ROOT / "recipes" / "suture_expert_servo.yaml",
        REPO_ROOT / "policies" / "presets" / "reference.json",
        REFERENCE_RESULTS,
    ),
    # The same motions under randomized appearance, trained with LeRobot's colour and sharpness transforms.
    "robust": Recipe(
        REPO_ROOT / "recipes" / "suture_expert_randomized.yaml",
        REPO_ROOT / "policies" / "presets" / "robust.json",
        REPO_ROOT / "docs" / "results" / "robust_noaffine_8000",
    ),
    # The reference's recipe with two equally valid approaches (the detectors' multimodality test).
    "two_sided": Recipe(
        REPO_ROOT / "recipes" / "suture_expert_two_sided.yaml",
        REPO_ROOT / "policies" / "presets" / "two_sided.json",
        REPO_ROOT / "docs" / "results" / "two_sided_5500",
    ),
}
STAGES = ("record", "train", "calibrate", "experiments")

_TOY_EXPERIMENTS = {
    "nominal_episodes": 2,
    "expert_episodes": 2,
    "needle_drop_runs": 1,
    "camera_moved_runs": 1,
    "phantom_servo_runs": 1,
    "phantom_moved_after_insertion_runs": 1,
    "cbf_runs": 1,
    "enforced_runs": 1,
    "batch_envs": 2,
}


@dataclass
class ReproduceConfig:
    """Args:
    recipe: which policy to make, one of :data:`RECIPES`: ``reference`` (the paper's scenarios),
        ``robust`` (randomized appearance and image augmentation) or ``two_sided`` (two demonstrated
        approaches).
    output_dir: where the dataset, the training run, the experiments, the comparison and the timings go.
    reference: a committed results folder whose ``metrics.json`` the new run is compared with (default:
        the recipe's own).
    toy: the same pipeline at toy scale (a smoke test; its table is not expected to match).
    device: torch device for calibration and experiments (training takes the preset's).
    """

    recipe: str = "reference"
    output_dir: Path = Path("outputs/reproduce")
    reference: Path | None = None
    toy: bool = False
    device: str = "cpu"

    def __post_init__(self):
        if self.recipe not in RECIPES:
            raise ValueError(f"`recipe` must be one of {list(RECIPES)}. Got {self.recipe!r}.")
        if self.reference is None:
            self.reference = RECIPES[self.recipe].results
        recipe = RECIPES[self.recipe]
        missing = [p for p in (recipe.dataset, recipe.train_preset, CALIBRATE_CONFIG) if not p.is_file()]
        if missing:
            raise ValueError(
                f"The recipe files {[str(p) for p in missing]} are missing: `reproduce` runs from a clone of "
                "the lerobot-suture repository (git clone, then `make reproduce`)."
            )
        if not (Path(self.reference) / "metrics.json").is_file() and self.reference != recipe.results:
            raise ValueError(
                f"`reference` must be a results folder holding metrics.json. Got {self.reference}."
            )


def record_stage(cfg: ReproduceConfig) -> Path:
    return record_recipe(RECIPES[cfg.recipe].dataset, cfg.output_dir / "data", cfg.toy)


def train_stage(cfg: ReproduceConfig, dataset_root: Path) -> Path:
    from lerobot_suture.datasets.split import train_episodes
    from lerobot_suture.datasets.video import resolve_video_backend
    from lerobot_suture.runtime.training import run_lerobot_train

    train_preset = RECIPES[cfg.recipe].train_preset
    preset = json.loads(train_preset.read_text())
    steps = 4 if cfg.toy else int(preset["steps"])
    fresh = [f"--config_path={train_preset}"]
    if cfg.toy:
        episodes = ",".join(str(i) for i in train_episodes(dataset_root))
        fresh += [f"--dataset.episodes=[{episodes}]", "--batch_size=4", "--num_workers=0", "--log_freq=1"]
    common = [
        f"--dataset.root={dataset_root}",
        f"--dataset.video_backend={resolve_video_backend()}",
        f"--save_freq={2 if cfg.toy else preset['save_freq']}",
    ]
    return run_lerobot_train(cfg.output_dir / "train", fresh, steps, common)


def calibrate_stage(cfg: ReproduceConfig, policy_dir: Path, dataset_root: Path) -> Path:
    return calibrate_policy(policy_dir, dataset_root, cfg.device, cfg.toy)


def experiments_stage(cfg: ReproduceConfig, policy_dir: Path, calibration_file: Path) -> dict:
    from lerobot_suture.experiments.paper import ExperimentsConfig, run_experiments
    from lerobot_suture.runtime.config import PolicyPathConfig

    out = cfg.output_dir / "experiments"
    metrics_file = out / "metrics.json"
    calibration = json.loads(calibration_file.read_text())
    # metrics.json and report.md are the experiments' last writes; metrics.json names its calibration.
    if metrics_file.is_file() and (out / "report.md").is_file():
        metrics = json.loads(metrics_file.read_text())
        if metrics["calibration"] == calibration:
            logger.info("experiments already run with this calibration: %s", out)
            return metrics
    counts = _TOY_EXPERIMENTS if cfg.toy else {}
    run_experiments(
        ExperimentsConfig(
            policy=PolicyPathConfig(path=policy_dir), output_dir=out, device=cfg.device, **counts
        )
    )
    return json.loads(metrics_file.read_text())


def write_comparison(cfg: ReproduceConfig, metrics: dict, timings: StageTimings) -> str:
    from lerobot_suture.experiments.compare import compare_metrics, comparison_json, comparison_markdown

    committed_file = Path(cfg.reference) / "metrics.json"
    if committed_file.is_file():
        rows = compare_metrics(json.loads(committed_file.read_text()), metrics)
        table = comparison_markdown(rows, f"committed ({Path(cfg.reference).name})", "this run")
    else:  # a recipe whose results are not committed yet: the new run's figures alone
        rows = compare_metrics(metrics, metrics)
        table = comparison_markdown(rows, "this run", "this run")
    stage_times = ", ".join(f"{s} {timings.seconds.get(s, 0.0) / 60:.1f} min" for s in STAGES)
    text = (
        f"# Reproduction{' (toy scale)' if cfg.toy else ''}\n\n{table}\n\n"
        f"Wall time {round(sum(timings.seconds.get(s, 0.0) for s in STAGES), 1) / 60:.1f} min ({stage_times}).\n"
    )
    (cfg.output_dir / "comparison.md").write_text(text)
    (cfg.output_dir / "comparison.json").write_text(
        json.dumps(
            {"toy": cfg.toy, "rows": comparison_json(rows), "timings_s": timings.seconds},
            separators=(",", ":"),
        )
    )
    return text


def run_reproduce(cfg: ReproduceConfig) -> str:
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    timings = StageTimings(cfg.output_dir / "timings.json")

    def timed(stage: str, fn, *args):
        logger.info("reproduce: stage %d of %d, %s", STAGES.index(stage) + 1, len(STAGES), stage)
        return timings.timed(stage, fn, *args)

    dataset_root = timed("record", record_stage, cfg)
    policy_dir = timed("train", train_stage, cfg, dataset_root)
    calibration_file = timed("calibrate", calibrate_stage, cfg, policy_dir, dataset_root)
    metrics = timed("experiments", experiments_stage, cfg, policy_dir, calibration_file)
    return write_comparison(cfg, metrics, timings)
