"""Metrics of policy rollouts (:class:`~lerobot_suture.runtime.rollout.EpisodeLog`): the gate's alarms,
the per-episode score traces, and the O.O.D. metrics of a scenario's runs against nominal runs.

The pure statistics (AUROC, intervals, delays) are :mod:`lerobot_suture.experiments.metrics`.
"""

from __future__ import annotations

import math

import numpy as np

from lerobot_suture.experiments import metrics
from lerobot_suture.runtime.rollout import EpisodeLog

# (id, scenario, title) of the paper's O.O.D. experiments.
EXPERIMENTS = (
    ("1", "needle_drop", "Experiment 1: needle dropped during execution"),
    ("2", "camera_moved", "Experiment 2: camera moved to an unseen viewpoint"),
    ("3.1", "phantom_servo", "Experiment 3.1: phantom moved during the approach"),
    ("3.2", "phantom_moved_after_insertion", "Experiment 3.2: phantom moved after insertion"),
)


def traces(logs: list[EpisodeLog]) -> list[dict]:
    """Per episode, what the figures and the O.O.D. metrics are computed from: the score and the
    gate's alarm at every control step, the onset and the outcome (``traces.json``).
    """
    return [
        {
            "seed": log.seed,
            "success": log.success,
            "onset_step": log.onset_step,
            "scores": [float(f"{x:.6g}") for x in log.scores],
            "alarms": [int(a) for a in alarms(log)],
        }
        for log in logs
    ]


def in_tissue_at_handover(log: EpisodeLog) -> bool:
    """Whether the needle was in tissue when the gate released control (before the surgeon acted)."""
    step = log.handover_step
    return bool(step) and log.steps[step - 1].needle_in_tissue  # no step before: the episode's start


def alarms(log: EpisodeLog) -> list[bool]:
    return [s.ood for s in log.steps]


def ood_metrics(nominal: list[EpisodeLog], runs: list[EpisodeLog]) -> dict:
    """Episode-level AUROC against nominal runs and TPR at the calibrated threshold, each with its 95%
    interval (DeLong; Wilson), and the detection delay."""
    onsets = [log.onset_step for log in runs]
    flagged = [
        onset is not None and metrics.first_alarm_after(alarms(log), onset) is not None
        for log, onset in zip(runs, onsets, strict=True)
    ]
    delays = metrics.detection_delays([(alarms(log), onset) for log, onset in zip(runs, onsets, strict=True)])
    nominal_maxima = [metrics.episode_score(log.scores) for log in nominal]
    run_maxima = [metrics.episode_score(log.scores) for log in runs]
    n_flagged = sum(flagged)
    return {
        "runs": len(runs),
        "auroc": metrics.auroc(nominal_maxima, run_maxima),
        "auroc_interval95": metrics.auroc_interval(nominal_maxima, run_maxima),
        "auroc_common_steps": metrics.auroc_over_common_steps(
            [log.scores for log in nominal], [log.scores for log in runs], onsets
        ),
        "tpr_at_threshold": n_flagged / len(runs) if runs else math.nan,
        "flagged_runs": n_flagged,
        "tpr_wilson95": metrics.wilson_interval(n_flagged, len(runs)),
        "detection_delay_steps": metrics.summarize(delays),
        "onset_step": metrics.summarize([o for o in onsets if o is not None]),
        "policy_success_rate": float(np.mean([log.success for log in runs])) if runs else math.nan,
    }
