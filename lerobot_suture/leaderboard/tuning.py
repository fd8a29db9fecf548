"""Each policy family's tuning budget, spent the same way: ``lerobot-suture leaderboard --tune=true``.

A family has up to three configurations (:data:`CONFIGURATIONS`): its committed preset, LeRobot's defaults for
our shapes where LeRobot has the policy, and one variant. Each is trained like the board's rows (the
insertion preset's training episodes and number of steps, the presets' seed) and evaluated on nominal and
insertion's scenarios on validation seeds, never on the test seeds (:func:`validation_base`). The
configuration with the highest mean success over those cells is chosen (ties: the higher nominal success,
then the earlier configuration). ``ensemble_member`` is the ensemble's member recipe, so it follows the
ensemble's choice rather than being tuned apart.

The run writes ``tuning.json`` and ``tuning.md`` (every configuration's flags and validation scores, and the
choice) into ``results_dir``, and each family's chosen configuration as a complete ``lerobot-train`` config,
``presets/FAMILY.json``, to commit as that family's preset. Every stage is resumable like the board's.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np

from lerobot_suture.leaderboard import cells
from lerobot_suture.leaderboard.pipeline import TASK_RECIPES, LeaderboardConfig, train_policy
from lerobot_suture.leaderboard.ray_stages import StageGraph
from lerobot_suture.leaderboard.run import add_stage_times, finished_row, raise_failures, submit_row
from lerobot_suture.pipelines.stages import StageTimings, record_recipe
from lerobot_suture.sim.tasks import TASK_NAMES

TUNING_TASK = "insertion"
VALIDATION_OFFSET = 500_000
"""Validation seeds start this far above the board's test seeds (``--seed``): no test seed is among them."""
CONFIGURATIONS: dict[str, dict[str, tuple[str, ...]]] = {
    "act": {
        "preset": (),
        # LeRobot's ACTConfig defaults, but for the ImageNet weights (no download at run time).
        "lerobot_defaults": (
            "--policy.chunk_size=100",
            "--policy.n_action_steps=100",
            "--policy.dim_model=512",
            "--policy.dim_feedforward=3200",
            "--policy.optimizer_lr=1e-05",
            "--policy.optimizer_lr_backbone=1e-05",
        ),
        "half_encoder": ("--policy.n_encoder_layers=2",),
    },
    "diffusion": {
        "preset": (),
        # LeRobot's DiffusionConfig defaults, but for the ImageNet weights (hence group norm) and our 96 px.
        "lerobot_defaults": (
            "--policy.n_obs_steps=2",
            "--policy.horizon=64",
            "--policy.n_action_steps=32",
            "--policy.drop_n_last_frames=7",
            "--policy.down_dims=[512,1024,2048]",
            "--policy.diffusion_step_embed_dim=128",
            "--policy.noise_scheduler_type=DDPM",
            "--policy.prediction_type=epsilon",
            "--policy.num_inference_steps=null",
            "--policy.optimizer_lr=0.0001",
            "--policy.optimizer_weight_decay=1e-06",
            "--policy.scheduler_warmup_steps=500",
        ),
        "wide_unet": ("--policy.down_dims=[128,256,512]",),
    },
    "ensemble_diffusion": {
        "preset": (),
        "wide_unet": ("--policy.down_dims=[128,256,512]",),
        "full_backbone": ("--policy.vision_backbone_stages=4",),
    },
}
"""Each family's configurations: flags on top of its preset (the board's ``act.json`` or ``diffusion.json``;
the task's ensemble preset)."""


def families(policies: list[str]) -> list[str]:
    """The families tuned for the board's ``policies`` (the member follows the ensemble)."""
    tuned = ["ensemble_diffusion" if p == "ensemble_member" else p for p in policies]
    return list(dict.fromkeys(tuned))


def validation_base(cfg: LeaderboardConfig) -> int:
    """The base of the validation seeds (:func:`cells.condition_seeds` takes it as the test seeds' base)."""
    return cfg.seed + VALIDATION_OFFSET


def choose(scores: dict[str, dict]) -> str:
    """The chosen configuration: the highest mean validation success, then nominal, then the earlier one."""
    order = list(scores)
    return max(order, key=lambda name: (scores[name]["mean"], scores[name]["nominal"], -order.index(name)))


def candidate_name(family: str, configuration: str) -> str:
    """The row name of a configuration's validation cells."""
    return f"{family}~{configuration}"


def run_tuning(cfg: LeaderboardConfig) -> dict:
    """Train and score every configuration of every family of ``cfg.policies``; write the report and presets."""
    check_validation_seeds_are_apart(cfg)
    validation = dataclasses.replace(cfg, seed=validation_base(cfg), shifts=[])
    task = TUNING_TASK
    graph = StageGraph(cfg.ray_address)
    timings = StageTimings(cfg.output_dir / "timings.json")
    root = cfg.output_dir / "data" / task
    dataset_root = graph.submit(
        f"record {task}", "record", record_recipe, TASK_RECIPES[task][0], root, cfg.toy
    )
    submitted, policy_dirs = {}, {}
    for family in families(cfg.policies):
        for configuration, flags in CONFIGURATIONS[family].items():
            name = candidate_name(family, configuration)
            policy_dirs[family, configuration] = graph.submit(
                f"train {task} {name}", "train", train_policy, cfg, task, family, dataset_root, None,
                configuration, flags, cpus=cfg.train_cpus,
            )  # fmt: skip
            submitted[family, configuration] = submit_row(
                graph, validation, task, name, policy_dirs[family, configuration], {}, shifts=[]
            )
    outputs, seconds, failures = graph.run("tuning")
    add_stage_times(graph, seconds, timings)
    report: dict = {
        "task": task,
        "validation_seed": validation.seed,
        "episodes": cfg.episodes,
        "families": {},
    }
    for family in families(cfg.policies):
        scores = {}
        for configuration, flags in CONFIGURATIONS[family].items():
            row = finished_row(submitted[family, configuration], outputs)
            if row is None:
                continue
            rates = {c: cell["success_rate"] for c, cell in row.items()}
            scores[configuration] = {
                "flags": list(flags),
                "validation": rates,
                "nominal": rates["nominal"],
                "mean": float(np.mean(list(rates.values()))),
            }
        entry: dict = {"configurations": scores}
        if len(scores) == len(CONFIGURATIONS[family]):
            entry["chosen"] = chosen = choose(scores)
            trained = outputs[f"train {task} {candidate_name(family, chosen)}"]
            preset = Path(cfg.results_dir) / "presets" / f"{family}.json"
            preset.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(Path(trained) / "train_config.json", preset)
            entry["preset"] = str(preset)
        report["families"][family] = entry
    results = Path(cfg.results_dir)
    results.mkdir(parents=True, exist_ok=True)
    (results / "tuning.json").write_text(json.dumps(report, indent=1))
    (results / "tuning.md").write_text(render_tuning(report))
    raise_failures(failures, cfg.output_dir)
    return report


def render_tuning(report: dict) -> str:
    """The tuning report as markdown: per family, each configuration's validation success and the choice."""
    lines = [
        "# Tuning",
        "",
        f"Each family's configurations on {report['task']}, trained like the board's rows and scored on "
        f"{report['episodes']} validation episodes a condition (seeds from {report['validation_seed']}, apart "
        "from the test seeds): success % on nominal, the mean over the scenarios, and the mean over all of them, "
        "which chooses.",
        "",
        "| family | configuration | flags on the preset | nominal | scenarios | mean | chosen |",
        "|---|---|---|---|---|---|---|",
    ]
    for family, entry in report["families"].items():
        for configuration, s in entry["configurations"].items():
            scenarios = [r for c, r in s["validation"].items() if c != "nominal"]
            flags = " ".join(f"`{f}`" for f in s["flags"]) or "(none)"
            lines.append(
                f"| {family} | {configuration} | {flags} | {100 * s['nominal']:.0f} | "
                f"{100 * float(np.mean(scenarios)) if scenarios else float('nan'):.0f} | {100 * s['mean']:.0f} | "
                f"{'yes' if entry.get('chosen') == configuration else ''} |"
            )
    return "\n".join(lines) + "\n"


def check_validation_seeds_are_apart(cfg: LeaderboardConfig) -> None:
    """Raise if a validation seed of insertion is a test seed of any task (a ``--seed`` too close to another)."""
    test = {
        s
        for t in TASK_NAMES
        for c in cells.conditions(t, cfg.shifts)
        for s in cells.condition_seeds(cfg.seed, t, c, cfg.episodes)
    }
    shared = test & {
        s
        for c in cells.conditions(TUNING_TASK, [])
        for s in cells.condition_seeds(validation_base(cfg), TUNING_TASK, c, cfg.episodes)
    }
    if shared:
        raise ValueError(f"{len(shared)} validation seeds are test seeds; the tuning would see the test.")
