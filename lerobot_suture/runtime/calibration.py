"""Fitting a policy's O.O.D. gate on its nominal rollouts: ``lerobot-suture calibrate`` for an ensemble's own
gate, ``lerobot-suture calibrate-stac`` for STAC on any chunking policy (ACT, diffusion, ...).

``calibrate`` rolls the policy out in the nominal scenario on seeds it was not trained on (the dataset's validation
seeds when ``dataset_root`` is given, else fresh seeds), records the uncertainty score of every
prediction, fits the in-distribution model on the first ``calibration_episodes`` episodes, measures
the false-alarm rate on the remaining held-out episodes, and writes the calibration into the policy
directory, where ``from_pretrained`` finds it.

The episodes are of the dataset's task (``--task`` of ``lerobot-suture record``; ``insertion`` without a
dataset), so a policy trained on a running suture is calibrated on running sutures.

A dataset recorded with appearance randomization (``--appearance.*``) lends its ranges too, so the gate is
calibrated on the look the policy was trained on: what the randomization made in-distribution is not
flagged, and what lies beyond its ranges still is.

``calibrate-stac`` rolls the policy out in the nominal scenario on fresh seeds, scores every chunk it predicts
against the one before (:class:`~lerobot_suture.runtime.gates.StacGates`), and sets the per-episode threshold at
the split-conformal quantile of the episodes' maxima. It measures the false-alarm rate on further held-out
episodes and writes ``stac_calibration.json`` and ``stac_calibration_report.json`` beside the policy, where the
env path and ``lerobot-rollout --strategy.type=gated_dagger`` read it.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from lerobot_suture.datasets.metadata import read_episode_log, write_json_atomic
from lerobot_suture.runtime.config import PolicyCommandConfig, PolicyPathConfig, RolloutCommandConfig
from lerobot_suture.runtime.gates import PolicyGates, SilentGates, StacGates, StageGates
from lerobot_suture.runtime.policy import copy_with_overrides, env_kwargs_for_policy, reporting_runner
from lerobot_suture.runtime.rollout import EpisodeLog, make_scenario_env, rollout_seeds
from lerobot_suture.runtime.rollout_calibration import rollout_scores
from lerobot_suture.runtime.seeds import fresh_seeds
from lerobot_suture.safety.ood.calibration import (
    conformal_episode_threshold,
    default_model,
    fit_calibration,
    min_calibration_episodes,
)
from lerobot_suture.safety.ood.calibration_file import (
    StacCalibration,
    calibration_report_file,
    save_calibration,
)
from lerobot_suture.safety.ood.likelihood_ratio import false_alarm_rates
from lerobot_suture.safety.ood.stage_gate import StageThresholds, fit_stage_thresholds, segment_runs

logger = logging.getLogger(__name__)

LOW_CALIBRATION_SUCCESS = 0.5
"""Below this success rate on its calibration episodes, a policy's gate is calibrated on failures: warned."""

SCORE_CHOICE_FIELDS = ("uncertainty_score", "uncertainty_space", "uncertainty_source", "uncertainty_steps")
"""The ensemble's config fields that choose how a prediction is scored (``lerobot-suture score-study``)."""

STAC_REPORT_FILE = "stac_calibration_report.json"
STAC_SEED_OFFSET = 400_000
"""STAC's calibration seeds are fresh seeds from this offset on (apart from the env path's other fresh seeds)."""


@dataclass
class CalibrateConfig(RolloutCommandConfig):
    """Args (and those of :class:`~lerobot_suture.runtime.config.RolloutCommandConfig`):
    dataset_root: a ``lerobot-suture record`` dataset whose validation seeds are used first.
    calibration_episodes: nominal episodes the in-distribution model is fitted on. In ``per_episode`` mode
        the threshold is an order statistic of their maxima: with 24 it is the largest, whose false-alarm
        rate on new episodes scatters widely around alpha; 100 pin it to about +-2% (binomial spread of
        the order statistic). Validation seeds come first, then fresh ones.
    holdout_episodes: further nominal episodes on which the false-alarm rate is measured.
    model: ``normal`` (the paper's) or ``lognormal`` (the score is positive and skewed). Unset:
        ``lognormal``, or ``normal`` for the ``logdet`` score, which can be negative.
    mode: ``per_prediction`` (the paper's test on every prediction) or ``per_episode`` (a threshold on
        the running maximum holding the per-episode false-alarm rate near alpha).
    alpha: significance of the one-sided likelihood-ratio test.
    h: width factor of the in-distribution model, Normal(mean, h * std).
    uncertainty_score, uncertainty_space, uncertainty_source, uncertainty_steps: a choice of score (e.g.
        from ``lerobot-suture score-study``) to calibrate the gate for; it is written into the policy's
        ``config.json`` beside the calibration. Unset: the policy's own.
    copy_to: calibrate a copy of the policy made there instead (an empty or new directory), with
        ``--policy.num_inference_steps`` / ``--policy.uncertainty_samples_per_member`` written into its
        ``config.json``: the gate of an inference approximation (the original is left as it is).
    per_stage: also fit a gate per stage of the running suture (``stage_calibration.json``): each subtask's
        threshold from the largest score of its segments in the calibration episodes that succeeded, at
        ``stage_alpha`` per segment (FAIL-Detect's convention; needs a running-suture policy and workers=1).
    stage_alpha: the per-segment false-alarm rate of the stage gate (0.01: about 10% over a suture's twelve
        segments; the quantile needs at least 99 successful segments of each subtask).
    rollouts: fit on the nominal rollouts recorded at this LeRobotDataset root by
        ``lerobot-rollout --strategy.type=gated_dagger`` instead of rolling the policy out on the env path: the
        gate of an inference engine that predicts at another cadence (real-time chunking,
        :mod:`~lerobot_suture.runtime.rollout_calibration`).
    calibration_file: the file written into the policy directory (with ``<stem>_report.json``). Unset: the
        policy's ``ood.calibration_file``. A policy reads another with ``--policy.ood.calibration_file=NAME``.
    """

    dataset_root: Path | None = None
    calibration_episodes: int = 100
    holdout_episodes: int = 20
    model: str | None = None
    mode: str = "per_episode"
    alpha: float = 0.05
    h: float = 1.0
    uncertainty_score: str | None = None
    uncertainty_space: str | None = None
    uncertainty_source: str | None = None
    uncertainty_steps: str | None = None
    copy_to: Path | None = None
    per_stage: bool = False
    stage_alpha: float = 0.01
    rollouts: Path | None = None
    calibration_file: str | None = None

    @property
    def writes_to_policy(self) -> bool:
        """Into the policy's own directory unless a copy is calibrated (the overrides then go into it)."""
        return self.copy_to is None

    def __post_init__(self):
        super().__post_init__()
        if self.calibration_episodes < 1 or self.holdout_episodes < 0:
            raise ValueError(
                "`calibration_episodes` must be >= 1 and `holdout_episodes` >= 0. "
                f"Got {self.calibration_episodes}, {self.holdout_episodes}."
            )
        if self.mode == "per_episode" and self.calibration_episodes < min_calibration_episodes(self.alpha):
            raise ValueError(
                f"`mode=per_episode` at alpha={self.alpha} needs at least "
                f"{min_calibration_episodes(self.alpha)} calibration episodes. Got {self.calibration_episodes}; "
                "raise `--calibration_episodes` or use `--mode=per_prediction`."
            )
        if not 0 < self.stage_alpha < 0.5:
            raise ValueError(f"`stage_alpha` must be in (0, 0.5). Got {self.stage_alpha!r}.")
        if self.rollouts is not None and (self.per_stage or self.copy_to is not None or self.score_choice()):
            raise ValueError(
                "`rollouts` fits the gate the recorded rollouts were scored with, into the policy itself: drop "
                "`per_stage`, `copy_to` and the score settings, or calibrate on the env path without `rollouts`."
            )
        if self.calibration_file is not None and (
            not self.calibration_file.endswith(".json")
            or Path(self.calibration_file).name != self.calibration_file
        ):
            raise ValueError(
                f"`calibration_file` must be a plain .json file name. Got {self.calibration_file!r}."
            )
        if self.per_stage and self.workers != 1:
            raise ValueError(
                f"`per_stage` reads each env's subtask in this process: calibrate at `workers`=1. Got {self.workers}."
            )

    def score_choice(self) -> dict[str, str]:
        """The score settings given on the command line (field -> value)."""
        return {name: getattr(self, name) for name in SCORE_CHOICE_FIELDS if getattr(self, name) is not None}


def apply_score_choice(config, choice: dict[str, str]) -> None:
    """Set a score choice on a loaded ensemble config; the config's own validation judges it."""
    if not choice:
        return
    if not hasattr(config, "score_choices"):
        raise ValueError(f"A {config.type!r} policy has no score settings; drop {sorted(choice)}.")
    dataclasses.replace(config, **choice)  # raises, naming the field, for a value the config refuses
    for name, value in choice.items():
        setattr(config, name, value)


def write_score_choice(policy_dir: Path, choice: dict[str, str]) -> None:
    """Record a score choice in the policy's ``config.json`` (only those fields change, atomically)."""
    if not choice:
        return
    path = Path(policy_dir) / "config.json"
    write_json_atomic(path, {**json.loads(path.read_text()), **choice})


def calibration_seeds(cfg: CalibrateConfig) -> list[int]:
    """Seeds of the calibration then the held-out episodes: validation seeds first, then fresh ones."""
    needed = cfg.calibration_episodes + cfg.holdout_episodes
    seeds: list[int] = []
    if cfg.dataset_root is not None:
        from lerobot_suture.datasets.split import validation_seeds

        seeds = validation_seeds(cfg.dataset_root)[:needed]
    seeds += fresh_seeds(needed - len(seeds))
    return seeds


def dataset_appearance(dataset_root: Path | None) -> dict:
    """``{"appearance": ranges}`` when the dataset at ``dataset_root`` was recorded with appearance
    randomization, else ``{}`` (no dataset, or a dataset of the scene's own look)."""
    if dataset_root is None:
        return {}
    appearance = read_episode_log(dataset_root)["env_kwargs"].get("appearance")
    return {"appearance": appearance} if appearance else {}


def dataset_task(dataset_root: Path | None) -> dict:
    """``{"task": name}`` when the dataset at ``dataset_root`` was recorded on a task other than
    ``insertion`` (only those logs name it), else ``{}``."""
    if dataset_root is None:
        return {}
    task = read_episode_log(dataset_root)["env_kwargs"].get("task")
    return {"task": task} if task else {}


def collect_scores(
    runner,
    env_kwargs: dict,
    seeds: list[int],
    desc: str,
    batch_envs: int = 8,
    workers: int = 1,
    gates: SilentGates | None = None,
    scenario: str = "nominal",
) -> tuple[np.ndarray, np.ndarray, list[EpisodeLog]]:
    """Per-prediction scores (of ``gates``, by default the policy's own) and their episode ids over episodes of
    ``runner`` in ``scenario``."""
    logs = rollout_seeds(
        functools.partial(make_scenario_env, env_kwargs, scenario),
        runner,
        seeds,
        batch_envs,
        desc=desc,
        workers=workers,
        gates=gates,
    )
    scores, episode_ids = [], []
    for episode, log in enumerate(logs):
        for step in log.steps:
            if step.new_prediction:
                scores.append(step.score)
                episode_ids.append(episode)
    return np.asarray(scores), np.asarray(episode_ids), logs


def stage_thresholds(
    logs: list[EpisodeLog], alpha: float, subtasks: Sequence[str] | None = None
) -> StageThresholds:
    """A gate per stage fitted on ``logs`` (rolled out with :class:`StageGates`, so each step names its subtask):
    each subtask's segments in the episodes that succeeded (FAIL-Detect's convention). ``subtasks``: only these
    (a chain's learned subtasks, where a scripted one scores only when it falls back to a policy), else all."""
    scores, stages, segments, successful = [], [], [], []
    segment = -1
    for log in logs:
        for subtask, _, start, stop in segment_runs([s.subtask for s in log.steps]):
            segment += 1
            if not subtask or (subtasks is not None and subtask not in subtasks):
                continue
            for step in log.steps[start:stop]:
                if step.new_prediction and step.consulted:
                    scores.append(step.score)
                    stages.append(subtask)
                    segments.append(segment)
                    successful.append(log.success)
    return fit_stage_thresholds(scores, stages, segments, successful, alpha)


def episode_maxima(scores: np.ndarray, episode_ids: np.ndarray, episodes: int) -> np.ndarray:
    """(episodes,) each episode's largest score (0 for an episode without one: STAC's first chunk scores 0)."""
    maxima = np.zeros(episodes)
    np.maximum.at(maxima, episode_ids.astype(int), scores)
    return maxima


def fit_gate(cfg: CalibrateConfig, config, scores: np.ndarray, episode_ids: np.ndarray):
    """The gate of the policy config ``config`` (its score and settings) fitted on ``scores`` of episodes
    ``episode_ids`` with the command's model, h, alpha and mode."""
    return fit_calibration(
        scores,
        model=cfg.model or default_model(config.uncertainty_score),
        h=cfg.h,
        alpha=cfg.alpha,
        mode=cfg.mode,
        episode_ids=episode_ids,
        score_name=config.uncertainty_score,
        space=config.uncertainty_space,
        score_settings=config.score_settings(),
    )


def write_report(policy_dir: Path, calibration_file: str, report: dict) -> None:
    """``report`` as ``<stem>_report.json`` beside the calibration file."""
    (Path(policy_dir) / calibration_report_file(calibration_file)).write_text(
        json.dumps(report, separators=(",", ":"))
    )


def run_calibration(cfg: CalibrateConfig) -> dict:
    """Fit the gate, write it beside the policy with ``ood_calibration_report.json``; returns the report."""
    if cfg.copy_to is not None:
        copy = copy_with_overrides(cfg.policy.path, cfg.copy_to, cfg.policy.overrides)
        cfg = dataclasses.replace(cfg, policy=PolicyPathConfig(path=copy), copy_to=None)
        logger.info("calibrating the copy %s", copy)
    runner = reporting_runner(cfg.policy.path, cfg.device)
    config = runner.policy.config
    calibration_file = cfg.calibration_file or config.ood.calibration_file
    if cfg.rollouts is not None:
        scores, ids, recorded = rollout_scores(cfg.rollouts, cfg.mode, cfg.alpha)
        calibration = fit_gate(cfg, config, scores, ids)
        path = save_calibration(calibration, cfg.policy.path, filename=calibration_file)
        report = {
            "calibration_file": str(path),
            "calibration": calibration.to_dict(),
            **recorded,
            "rtc_score": config.rtc_score,  # what the gate read, had the rollouts run under real-time chunking
        }
        write_report(cfg.policy.path, calibration_file, report)
        return report
    choice = cfg.score_choice()
    if choice and cfg.workers != 1:
        raise ValueError(
            "A score choice is applied to the policy in this process: calibrate with it at `workers`=1. "
            f"Got workers={cfg.workers}."
        )
    apply_score_choice(config, choice)
    env_kwargs = {
        **env_kwargs_for_policy(config),
        **dataset_appearance(cfg.dataset_root),
        **dataset_task(cfg.dataset_root),
    }
    seeds = calibration_seeds(cfg)
    fit_seeds, holdout_seeds = seeds[: cfg.calibration_episodes], seeds[cfg.calibration_episodes :]
    stage_gates = StageGates(PolicyGates(runner.policy), None) if cfg.per_stage else None
    scores, ids, fit_logs = collect_scores(
        runner, env_kwargs, fit_seeds, "calibration episodes", cfg.batch_envs, cfg.workers, stage_gates
    )
    # Fitted before anything is written: a stage gate that cannot be fitted leaves the policy as it was.
    stages = stage_thresholds(fit_logs, cfg.stage_alpha) if cfg.per_stage else None
    calibration = fit_gate(cfg, config, scores, ids)
    path = save_calibration(calibration, cfg.policy.path, filename=calibration_file)
    write_score_choice(cfg.policy.path, choice)  # only now that a calibration fitted for it is there
    report = {
        "calibration_file": str(path),
        "score_choice_written": choice,
        "calibration": calibration.to_dict(),
        "calibration_seeds": fit_seeds,
        "calibration_appearance": env_kwargs.get("appearance"),
        "calibration_task": env_kwargs.get("task", "insertion"),
        "calibration_success_rate": float(np.mean([log.success for log in fit_logs])),
    }
    if report["calibration_success_rate"] < LOW_CALIBRATION_SUCCESS:
        logger.warning(
            "The policy succeeded in %.0f%% of its %d calibration episodes: the gate takes what it did there "
            "for normal, so it flags little of what goes wrong. Calibrate a policy that does the task (train "
            "it longer or on more demonstrations), or read the gate's rates with this in mind.",
            100 * report["calibration_success_rate"],
            len(fit_seeds),
        )
    if stages is not None:
        report["stage_calibration_file"] = str(stages.save(cfg.policy.path))
        report["stage_calibration"] = asdict(stages)
    if holdout_seeds:
        held_scores, held_ids, held_logs = collect_scores(
            runner, env_kwargs, holdout_seeds, "held-out episodes", cfg.batch_envs, cfg.workers
        )
        rates = false_alarm_rates(held_scores, calibration, held_ids)
        report["holdout_seeds"] = holdout_seeds
        report["holdout_false_alarm_rate"] = asdict(rates)
        report["holdout_success_rate"] = float(np.mean([log.success for log in held_logs]))
    write_report(cfg.policy.path, calibration_file, report)
    return report


@dataclass
class CalibrateStacConfig(PolicyCommandConfig):
    """``lerobot-suture calibrate-stac`` flags, besides ``--policy.path`` (a chunking policy) and ``--device``.

    Args:
        calibration_episodes: nominal episodes the threshold is fitted on (>= 20 at alpha 0.05).
        holdout_episodes: further nominal episodes the false-alarm rate is measured on.
        alpha: per-episode false-alarm rate the threshold is set for, in (0, 0.5).
        bandwidth: STAC's kernel bandwidth per dimension (normalized action units, > 0).
    """

    writes_to_policy: ClassVar[bool] = True

    calibration_episodes: int = 100
    holdout_episodes: int = 20
    alpha: float = 0.05
    bandwidth: float = 0.5

    def __post_init__(self):
        super().__post_init__()
        if self.calibration_episodes < 1 or self.holdout_episodes < 0:
            raise ValueError(
                f"`calibration_episodes` must be >= 1 and `holdout_episodes` >= 0. Got "
                f"{self.calibration_episodes}, {self.holdout_episodes}."
            )


def stac_maxima(
    runner, gates: StacGates, env_kwargs: dict, seeds: list[int], desc: str, scenario: str = "nominal"
):
    """Each episode's largest STAC score, (E,), and the episodes' logs, one env at a time."""
    scores, ids, logs = collect_scores(
        runner, env_kwargs, seeds, desc, batch_envs=1, gates=gates, scenario=scenario
    )
    return episode_maxima(scores, ids, len(logs)), logs


def run_stac_calibration(cfg: CalibrateStacConfig) -> dict:
    """Fit the threshold, write the calibration and its report beside the policy; returns the report."""
    from lerobot_suture.runtime.policy import GateMode, PolicyRunner

    runner = PolicyRunner.from_pretrained(cfg.policy.path, GateMode.REPORT, cfg.device)
    gates = StacGates(runner.policy, bandwidth=cfg.bandwidth)
    seeds = fresh_seeds(cfg.calibration_episodes + cfg.holdout_episodes, start=STAC_SEED_OFFSET)
    try:
        maxima, logs = stac_maxima(
            runner, gates, env_kwargs_for_policy(runner.policy.config), seeds, "STAC calibration"
        )
    finally:
        gates.close()
    fit, held_out = maxima[: cfg.calibration_episodes], maxima[cfg.calibration_episodes :]
    threshold = conformal_episode_threshold(fit, cfg.alpha)
    config = runner.policy.config
    calibration = StacCalibration(
        threshold=threshold,
        bandwidth=cfg.bandwidth,
        alpha=cfg.alpha,
        episodes=len(fit),
        policy_type=str(config.type),
        n_action_steps=int(getattr(config, "n_action_steps", 1)),
    )
    path = calibration.save(cfg.policy.path)
    report = {
        "calibration": asdict(calibration),
        "calibration_seeds": seeds[: cfg.calibration_episodes],
        "holdout_seeds": seeds[cfg.calibration_episodes :],
        "calibration_success_rate": float(np.mean([log.success for log in logs[: cfg.calibration_episodes]])),
        "holdout_false_alarm_rate": float(np.mean(held_out > threshold)) if len(held_out) else math.nan,
        "calibration_file": str(path),
    }
    (Path(cfg.policy.path) / STAC_REPORT_FILE).write_text(json.dumps(report, separators=(",", ":")) + "\n")
    return report
