"""How ``lerobot-suture benchmark-ood`` scores its saved rollouts: each detector's held per-step scores,
its per-episode threshold, and the metrics per scenario, per shift and per phase of the episode."""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np

from lerobot_suture.detectors import PredictionFeatures, make_detector, timed_scores
from lerobot_suture.experiments import metrics
from lerobot_suture.experiments.paper import EXPERIMENTS, ood_metrics
from lerobot_suture.runtime.rollout import EpisodeLog
from lerobot_suture.safety.ood.calibration import conformal_episode_threshold

SCENARIOS = tuple(scenario for _, scenario, _ in EXPERIMENTS)


def prediction_features(
    captured: dict[str, np.ndarray], action_start: int, state_dim: int | None = None
) -> list[PredictionFeatures]:
    """One :class:`PredictionFeatures` per captured prediction, each linked to its episode's previous one.

    With ``state_dim``, each prediction's state is read from its embedding: LeRobot's diffusion
    conditioning is, per observation step, the state followed by the image features, flattened over the
    ``action_start + 1`` observation steps; the state is the last step's first ``state_dim`` entries."""
    out = []
    for i in range(len(captured["episode"])):
        first = i == 0 or captured["episode"][i - 1] != captured["episode"][i]
        embedding = captured["embedding"][i]
        state = None
        if state_dim is not None:
            state = embedding[0].reshape(action_start + 1, -1)[-1, :state_dim]
        out.append(
            PredictionFeatures(
                samples=captured["samples"][i],
                action_start=action_start,
                embedding=embedding,
                single_member_samples=captured["single"][i],
                previous_samples=None if first else captured["samples"][i - 1],
                shift=None if first else int(captured["step"][i] - captured["step"][i - 1]),
                state=state,
            )
        )
    return out


def hold_scores(pred_steps: np.ndarray, pred_scores: np.ndarray, n_steps: int) -> np.ndarray:
    """Per control step, the score of the latest prediction at or before it (as the gate holds it):
    (n_steps,) from predictions made at ``pred_steps`` (P,), ascending, the first at step 0."""
    if len(pred_steps) == 0 or pred_steps[0] != 0:
        raise ValueError("An episode's first prediction is made at its first control step.")
    index = np.searchsorted(pred_steps, np.arange(n_steps), side="right") - 1  # (n_steps,)
    return np.asarray(pred_scores, dtype=np.float64)[index]


def score_part(
    detector, logs: list[EpisodeLog], captured: dict, action_start: int, state_dim: int | None = None
) -> tuple[list, float]:
    """Per episode of a part, its held per-step scores; and the detector's seconds per prediction."""
    scores, seconds = timed_scores(detector, prediction_features(captured, action_start, state_dim))
    out = []
    for e, log in enumerate(logs):
        mine = captured["episode"] == e
        out.append(hold_scores(captured["step"][mine], scores[mine], len(log.steps)))
    return out, seconds


def with_detector(log: EpisodeLog, scores: np.ndarray, threshold: float) -> EpisodeLog:
    """``log`` with the detector's scores and its latched per-episode alarms (running max > threshold)."""
    alarms = np.fmax.accumulate(scores) > threshold
    steps = [
        replace(s, score=float(x), ood=bool(a), threshold=threshold)
        for s, x, a in zip(log.steps, scores, alarms, strict=True)
    ]
    return replace(log, steps=steps)


def shift_metrics(nominal: list[EpisodeLog], runs: list[EpisodeLog]) -> dict:
    """Under a shift: the policy's success, and whether the detector flags the runs that fail and spares
    those that succeed (its alarm anywhere in the run), beside the AUROC against nominal runs; and per
    run its largest score and its outcome, from which any other threshold's flags follow."""
    failed = [log.first_alarm_step is not None for log in runs if not log.success]
    succeeded = [log.first_alarm_step is not None for log in runs if log.success]
    m = ood_metrics(nominal, runs)
    episodes = nominal + runs
    return {
        "runs": len(runs),
        "success_rate": float(np.mean([log.success for log in runs])) if runs else math.nan,
        "auroc": m["auroc"],
        "flagged_of_failures": float(np.mean(failed)) if failed else math.nan,
        "flagged_of_successes": float(np.mean(succeeded)) if succeeded else math.nan,
        "failures": len(failed),
        "failure_prediction_balanced_accuracy": metrics.failure_prediction_balanced_accuracy(
            [log.first_alarm_step for log in episodes], [_failure_step(log) for log in episodes]
        ),
        "run_max_scores": [metrics.episode_score(log.scores) for log in runs],
        "run_successes": [bool(log.success) for log in runs],
    }


def approach_alarms(nominal: list[EpisodeLog], approach_steps: int) -> dict:
    """Where the nominal alarms fall: raised within the first ``approach_steps`` control steps (while the
    strategies of a two-sided policy split) or later; and the median ratio of each episode's largest
    score in the approach to its largest after it (above 1: the approach scores higher)."""
    first = [log.first_alarm_step for log in nominal if log.first_alarm_step is not None]
    ratios = [
        float(log.scores[:approach_steps].max() / log.scores[approach_steps:].max())
        for log in nominal
        if len(log.scores) > approach_steps and log.scores[approach_steps:].max() > 0
    ]
    return {
        "alarms": len(first),
        "in_approach": int(sum(s < approach_steps for s in first)),
        "approach_to_rest_max_ratio": float(np.median(ratios)) if ratios else math.nan,
    }


def _failure_step(log: EpisodeLog) -> int | None:
    return None if log.success else len(log.steps) - 1


def scenario_metrics(nominal: list[EpisodeLog], runs: list[EpisodeLog]) -> dict:
    """The experiments' O.O.D. metrics plus false alarms before the onset and failure prediction."""
    m = ood_metrics(nominal, runs)
    early = [
        log.first_alarm_step is not None and (log.onset_step is None or log.first_alarm_step < log.onset_step)
        for log in runs
    ]
    m["false_alarm_before_onset_per_episode"] = float(np.mean(early)) if runs else math.nan
    episodes = nominal + runs
    m["failure_prediction_balanced_accuracy"] = metrics.failure_prediction_balanced_accuracy(
        [log.first_alarm_step for log in episodes], [_failure_step(log) for log in episodes]
    )
    m["failed_runs"] = sum(not log.success for log in runs)
    return m


def evaluate_detector(
    name: str,
    parts: dict[str, tuple[list[EpisodeLog], dict]],
    action_start: int,
    alpha: float,
    shifts: list[str] = (),
    approach_steps: int = 20,
    state_dim: int | None = None,
) -> dict:
    """One detector: fitted on ``fit``, thresholded on ``calibration`` at per-episode level ``alpha``,
    measured on the test parts (the paper's scenarios and the ``shifts`` parts). ``state_dim``: the size
    of the policy's state, which detectors that read it need (see :func:`prediction_features`)."""
    detector = make_detector(name)
    fit_logs, fit_captured = parts["fit"]
    start = time.perf_counter()
    detector.fit(prediction_features(fit_captured, action_start, state_dim))
    fit_seconds = time.perf_counter() - start
    calibration, _ = score_part(detector, *parts["calibration"], action_start, state_dim)
    threshold = conformal_episode_threshold([s.max() for s in calibration], alpha)
    seconds, predictions, control_steps = 0.0, 0, 0
    scored: dict[str, list[EpisodeLog]] = {}
    for part in ("nominal", *SCENARIOS, *shifts):
        logs, captured = parts[part]
        per_episode, per_call = score_part(detector, logs, captured, action_start, state_dim)
        seconds += per_call * len(captured["episode"])
        predictions += len(captured["episode"])
        control_steps += sum(len(log.steps) for log in logs)
        scored[part] = [with_detector(log, s, threshold) for log, s in zip(logs, per_episode, strict=True)]
    nominal = scored["nominal"]
    result = {
        "threshold": threshold,
        "false_alarms": metrics.alarm_rates([[s.ood for s in log.steps] for log in nominal]),
        "cost": {
            "ms_per_prediction": 1e3 * seconds / max(predictions, 1),
            # The score is computed at new predictions only and held in between.
            "ms_per_control_step": 1e3 * seconds / max(control_steps, 1),
            "fit_s": fit_seconds,
        },
        "scenarios": {s: scenario_metrics(nominal, scored[s]) for s in SCENARIOS},
        "shifts": {s: shift_metrics(nominal, scored[s]) for s in shifts},
        "approach": approach_alarms(nominal, approach_steps),
    }
    result["mean_auroc"] = _mean([m["auroc"] for m in result["scenarios"].values()])
    result["mean_auroc_common_steps"] = _mean([m["auroc_common_steps"] for m in result["scenarios"].values()])
    result["traces"] = {
        part: [
            {"scores": log.scores.tolist(), "onset": log.onset_step, "success": log.success} for log in logs
        ]
        for part, logs in scored.items()
    }
    return result


def _mean(values: list[float]) -> float:
    finite = [v for v in values if v is not None and not math.isnan(v)]
    return float(np.mean(finite)) if finite else math.nan
