"""The presets and recipes parse as their commands parse them, and reference.json is the reference run.

``policies/presets/*.json`` go through ``TrainPipelineConfig.from_pretrained`` and ``validate``, as
``lerobot-train --config_path=...`` does; the reference preset's fields are compared with the training
config and the calibration report that the reference run committed in ``docs/results/``.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import fields
from pathlib import Path

import draccus
import pytest
import yaml

REPO_ROOT = Path(__file__).resolve().parents[1]
PRESETS = REPO_ROOT / "policies" / "presets"
DATASETS = REPO_ROOT / "recipes"
REFERENCE_RUN = REPO_ROOT / "docs" / "results" / "prior_servo_5500"
SCORE_CHOICE = ("uncertainty_score", "uncertainty_space", "uncertainty_source", "uncertainty_steps")
# Filled from the dataset by lerobot-train (features), or where the run's files were (paths).
NOT_IN_A_PRESET = {"input_features", "output_features", "needle_keypoints_dim", "pretrained_path"}
PIPELINE_FIELDS = ("seed", "batch_size", "steps", "num_workers", "save_freq", "env_eval_freq", "resume")


def _parse_train_config(path: Path, tmp_path: Path, *cli_args: str):
    """A train config file parsed and validated as ``lerobot-train --config_path=PATH`` does."""
    import lerobot_policy_ensemble_diffusion  # noqa: F401  (registers the policy type, as the plugin loader does)
    from lerobot.configs.train import TrainPipelineConfig

    cfg = TrainPipelineConfig.from_pretrained(str(path), cli_args=list(cli_args))
    cfg.output_dir = tmp_path / "train"  # must not exist yet
    cfg.validate()
    return cfg


@pytest.mark.parametrize("preset", sorted(p.stem for p in PRESETS.glob("*.json")))
def test_every_preset_parses_as_lerobot_train_parses_it(preset, tmp_path):
    data = json.loads((PRESETS / f"{preset}.json").read_text())
    cli = [] if "dataset" in data else ["--dataset.repo_id=local/suture_expert"]
    cfg = _parse_train_config(PRESETS / f"{preset}.json", tmp_path, *cli)
    # Ours, or LeRobot's own ACT and diffusion (act.json, diffusion.json: the leaderboard's other rows).
    assert cfg.policy.type in ("ensemble_diffusion", "act", "diffusion")
    assert cfg.policy.pretrained_backbone_weights is None  # offline: never downloads weights
    assert cfg.policy.push_to_hub is False
    assert cfg.optimizer is not None
    assert cfg.scheduler is not None or cfg.policy.type == "act"  # LeRobot's ACT trains at a constant rate


def test_every_preset_is_described_in_the_presets_readme():
    readme = (PRESETS / "README.md").read_text()
    for path in sorted(PRESETS.glob("*.json")) + sorted(PRESETS.glob("*.yaml")):
        assert f"`{path.name}`" in readme, path.name


def test_reference_preset_is_the_reference_run(tmp_path):
    preset = _parse_train_config(PRESETS / "reference.json", tmp_path)
    run = _parse_train_config(REFERENCE_RUN / "train_config.json", tmp_path)
    calibration = json.loads((REFERENCE_RUN / "ood_calibration_report.json").read_text())

    for field in fields(preset.policy):
        if field.name in NOT_IN_A_PRESET or field.name in SCORE_CHOICE:
            continue
        assert getattr(preset.policy, field.name) == getattr(run.policy, field.name), field.name
    # The score the gate reads: chosen on validation seeds, written by `calibrate` beside its calibration.
    for name in SCORE_CHOICE:
        assert getattr(preset.policy, name) == calibration["score_choice_written"][name], name
    for name in PIPELINE_FIELDS:
        assert getattr(preset, name) == getattr(run, name), name
    assert preset.optimizer == run.optimizer and preset.scheduler == run.scheduler
    assert preset.dataset.repo_id == run.dataset.repo_id
    assert preset.dataset.episodes == run.dataset.episodes == list(range(99))
    assert (preset.dataset.eval_split, preset.dataset.image_transforms.enable) == (0.0, False)
    assert (run.dataset.eval_split, run.dataset.image_transforms.enable) == (0.0, False)
    # The essentials, spelled out.
    policy = preset.policy
    assert (policy.n_members, policy.prior_scale, policy.vision_backbone_stages) == (4, 1.0, 2)
    assert (policy.needle_keypoints_weight, policy.prediction_type, policy.use_amp) == (100.0, "sample", True)
    assert (preset.steps, preset.batch_size, preset.seed) == (5500, 16, 1000)


def test_reference_calibration_config_is_the_reference_calibration():
    from lerobot_suture.runtime.calibration import CalibrateConfig
    from lerobot_suture.safety.ood.calibration import default_model

    path = PRESETS / "reference_calibrate.yaml"
    cfg = draccus.parse(CalibrateConfig, config_path=str(path), args=["--policy.path=policy_dir"])
    calibration = json.loads((REFERENCE_RUN / "ood_calibration_report.json").read_text())["calibration"]
    assert str(cfg.policy.path) == "policy_dir"
    assert cfg.dataset_root == Path("data/suture_expert_servo")
    assert cfg.model == calibration["model"] == default_model(calibration["score_name"])
    assert (cfg.mode, cfg.alpha, cfg.h) == (calibration["mode"], calibration["alpha"], calibration["h"])
    assert cfg.calibration_episodes == calibration["n_episodes"]
    assert cfg.score_choice() == {}  # the score is the policy's own (reference.json)


def test_reference_dataset_recipe_parses_as_record_parses_it():
    from lerobot_suture.datasets.record_config import parse_config

    reference = parse_config([f"--config_path={DATASETS / 'suture_expert_servo.yaml'}"])
    paper = parse_config([f"--config_path={DATASETS / 'suture_expert.yaml'}", "--repo_id=local/x"])
    preset = json.loads((PRESETS / "reference.json").read_text())["dataset"]
    assert (reference.repo_id, reference.root) == (preset["repo_id"], preset["root"])
    assert reference.scenario == "phantom_servo"
    assert (reference.steps_after_success, reference.grasp_blind_expert) == (8, True)
    # Everything else as the paper's recipe: 133 episodes, the last 34 for validation (99 train).
    for name in ("num_episodes", "val_fraction", "obs_type", "image_size", "seed", "grasp", "video"):
        assert getattr(reference, name) == getattr(paper, name), name
    assert reference.num_episodes - math.ceil(reference.num_episodes * reference.val_fraction) == 99


@pytest.mark.parametrize("preset, dataset", [("robust", "randomized"), ("two_sided", "two_sided")])
def test_variant_presets_are_the_reference_on_other_data(preset, dataset, tmp_path):
    """The robust and two-sided recipes change the data (and the robust one LeRobot's image transforms and,
    for its wider data, a longer schedule), nothing else: their tables differ from the reference's by what
    the data teaches."""
    reference = _parse_train_config(PRESETS / "reference.json", tmp_path / "a")
    variant = _parse_train_config(PRESETS / f"{preset}.json", tmp_path / "b")
    assert variant.policy == reference.policy
    longer = {"robust": {"steps": 8000}}.get(preset, {})
    for name in PIPELINE_FIELDS:
        assert getattr(variant, name) == longer.get(name, getattr(reference, name)), name
    assert variant.dataset.repo_id == f"local/suture_expert_{dataset}"
    assert variant.dataset.episodes == reference.dataset.episodes
    recipe = yaml.safe_load((DATASETS / f"suture_expert_{dataset}.yaml").read_text())
    assert recipe["repo_id"] == variant.dataset.repo_id
    transforms = variant.dataset.image_transforms
    assert transforms.enable is (preset == "robust")
    if transforms.enable:
        # No affine: a shifted image with an unchanged jaw is what a phantom moved after insertion looks like.
        assert set(transforms.tfs) == {"brightness", "contrast", "saturation", "hue", "sharpness"}


@pytest.mark.parametrize(
    "task, recipe_name", [("pickup", "pickup"), ("extraction", "extraction"), ("running_suture", "running")]
)
def test_a_task_preset_is_the_reference_on_the_task_s_recipe(task, recipe_name, tmp_path):
    reference = _parse_train_config(PRESETS / "reference.json", tmp_path / "a")
    pickup = _parse_train_config(PRESETS / f"{task}.json", tmp_path / "b")
    assert pickup.policy == reference.policy
    for name in PIPELINE_FIELDS:
        assert getattr(pickup, name) == getattr(reference, name), name
    from lerobot_suture.datasets.record_config import parse_config

    recipe = parse_config([f"--config_path={DATASETS / f'suture_{recipe_name}.yaml'}"])
    assert recipe.task == task and (recipe.repo_id, recipe.root) == (
        pickup.dataset.repo_id,
        pickup.dataset.root,
    )
    assert pickup.dataset.episodes == list(range(99))  # the 99 training episodes of its 133
    assert recipe.num_episodes - math.ceil(recipe.num_episodes * recipe.val_fraction) == 99


@pytest.mark.slow
def test_latency_benchmark_times_a_preset_with_the_needle_target():
    """`benchmarks/ensemble_latency.py --preset reference` builds the policy although the preset trains an
    auxiliary needle target the benchmark's synthetic observation does not hold (it is no input)."""
    import subprocess
    import sys

    preset = json.loads((PRESETS / "reference.json").read_text())
    assert preset["policy"]["needle_keypoints_weight"] > 0  # else this test tests nothing
    out = subprocess.run(
        [sys.executable, "benchmarks/ensemble_latency.py", "--preset", "reference", "--n-members", "2"]
        + ["--warmup", "0", "--repeats", "1"],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    result = json.loads(out.stdout)["result"]
    assert result["n_members"] == 2 and result["batched_s"] > 0


@pytest.mark.parametrize(
    ("family", "configuration"),
    [
        (family, configuration)
        for family, configurations in __import__(
            "lerobot_suture.leaderboard.tuning", fromlist=["CONFIGURATIONS"]
        ).CONFIGURATIONS.items()
        for configuration in configurations
    ],
)
def test_every_tuning_configuration_parses_and_changes_only_its_flags(family, configuration, tmp_path):
    """A family's tuning configurations are its preset with their flags, as `lerobot-train` parses them;
    none downloads weights, and LeRobot's defaults for our shapes are LeRobot's own where LeRobot has the policy."""
    from lerobot_suture.leaderboard.pipeline import POLICY_PRESETS, TASK_RECIPES
    from lerobot_suture.leaderboard.tuning import CONFIGURATIONS, TUNING_TASK

    preset = POLICY_PRESETS.get(family, TASK_RECIPES[TUNING_TASK][1])
    flags = CONFIGURATIONS[family][configuration]
    base = _parse_train_config(preset, tmp_path / "base")
    cfg = _parse_train_config(preset, tmp_path / "candidate", *flags)
    assert (
        cfg.policy.pretrained_backbone_weights is None and cfg.steps == base.steps and cfg.seed == base.seed
    )

    def same(a, b) -> bool:
        return (
            tuple(a) == tuple(b) if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)) else a == b
        )

    changed = {
        f.name
        for f in dataclasses.fields(cfg.policy)
        if not same(getattr(cfg.policy, f.name), getattr(base.policy, f.name))
    }
    assert changed == {flag.split("=")[0].removeprefix("--policy.") for flag in flags}
    if configuration == "lerobot_defaults":
        lerobot_default = type(cfg.policy)()
        for name in changed:
            assert same(getattr(cfg.policy, name), getattr(lerobot_default, name)), name
