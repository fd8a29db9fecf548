"""Metrics of the paper's experiments, as pure functions of per-episode logs.

Scores are the ensemble's uncertainty per control step (the latest prediction's), alarms the gate's
decisions; an episode's onset is the first control step whose info said ``perturbed``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

END_OF_TASK_STEPS = 8
"""The end of the task: the last control steps of a successful nominal episode (as the needle emerges)."""


def wilson_interval(successes: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """95% Wilson score interval of a binomial proportion (default z); (nan, nan) when n = 0."""
    if n == 0:
        return math.nan, math.nan
    p = successes / n
    denom = 1 + z**2 / n
    centre = (p + z**2 / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z**2 / (4 * n**2)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def paired_change(before: Sequence[bool], after: Sequence[bool], z: float = 1.959963984540054) -> dict:
    """The change of a success rate between two runs of the same episodes (the same seeds, in order).

    ``change`` is after minus before; ``interval`` its 95% interval by Newcombe's hybrid score method for
    paired proportions (1998, method 10: the two Wilson intervals combined with the pairs' correlation,
    continuity-corrected); ``improved`` / ``worsened`` count the episodes that turned into a success / a
    failure; ``p_value`` is McNemar's exact two-sided test of no change (a binomial test on those two
    counts). nan figures (and ``p_value`` 1) when there are no episodes.
    """
    before, after = [bool(x) for x in before], [bool(x) for x in after]
    if len(before) != len(after):
        raise ValueError(f"Paired runs need as many episodes: {len(before)} before, {len(after)} after.")
    n = len(before)
    both = sum(b and a for b, a in zip(before, after, strict=True))
    improved = sum(a and not b for b, a in zip(before, after, strict=True))
    worsened = sum(b and not a for b, a in zip(before, after, strict=True))
    neither = n - both - improved - worsened
    discordant = improved + worsened
    tail = sum(math.comb(discordant, k) for k in range(min(improved, worsened) + 1)) / 2**discordant
    out = {"episodes": n, "improved": improved, "worsened": worsened, "p_value": min(1.0, 2 * tail)}
    if n == 0:
        return {**out, "before": math.nan, "after": math.nan, "change": math.nan, "interval": (math.nan,) * 2}
    p_after, p_before = (both + improved) / n, (both + worsened) / n
    lo_after, hi_after = wilson_interval(both + improved, n, z)
    lo_before, hi_before = wilson_interval(both + worsened, n, z)
    margins = (both + improved) * (worsened + neither) * (both + worsened) * (improved + neither)
    cross = both * neither - improved * worsened
    corrected = cross - n / 2 if cross > n / 2 else (cross if cross < 0 else 0.0)
    phi = corrected / math.sqrt(margins) if margins > 0 else 0.0
    change = p_after - p_before
    down = math.sqrt(
        (p_after - lo_after) ** 2
        - 2 * phi * (p_after - lo_after) * (hi_before - p_before)
        + (hi_before - p_before) ** 2
    )
    up = math.sqrt(
        (p_before - lo_before) ** 2
        - 2 * phi * (p_before - lo_before) * (hi_after - p_after)
        + (hi_after - p_after) ** 2
    )
    return {
        **out,
        "before": p_before,
        "after": p_after,
        "change": change,
        "interval": (max(-1.0, change - down), min(1.0, change + up)),
    }


def _pairwise_wins(negatives: Sequence[float], positives: Sequence[float]) -> np.ndarray:
    """(positives, negatives) matrix: 1 where the positive scores higher, 0.5 on a tie; NaN scores dropped."""
    neg = np.asarray([x for x in negatives if not math.isnan(x)], dtype=np.float64)
    pos = np.asarray([x for x in positives if not math.isnan(x)], dtype=np.float64)
    return (pos[:, None] > neg[None, :]) + 0.5 * (pos[:, None] == neg[None, :])


def auroc(negatives: Sequence[float], positives: Sequence[float]) -> float:
    """Area under the ROC curve: P(positive score > negative score) + 0.5 P(tie) (Mann-Whitney U).

    NaN scores are dropped; nan when either side is empty.
    """
    wins = _pairwise_wins(negatives, positives)
    return float(wins.mean()) if wins.size else math.nan


def auroc_interval(
    negatives: Sequence[float], positives: Sequence[float], z: float = 1.959963984540054
) -> tuple[float, float]:
    """95% interval of :func:`auroc` (default z) from DeLong's variance, clipped to [0, 1].

    DeLong et al. 1988: each positive's share of negatives below it and each negative's share of
    positives above it (ties count half); the AUROC's variance is the sum of their variances over their
    counts. (nan, nan) when either side has fewer than two scores. A perfectly separated pair of samples
    has zero variance, so its interval is a point.
    """
    wins = _pairwise_wins(negatives, positives)
    n_pos, n_neg = wins.shape
    if n_neg < 2 or n_pos < 2:
        return math.nan, math.nan
    area = float(wins.mean())
    variance = wins.mean(axis=1).var(ddof=1) / n_pos + wins.mean(axis=0).var(ddof=1) / n_neg
    half = z * math.sqrt(variance)
    return max(0.0, area - half), min(1.0, area + half)


def episode_score(scores: Sequence[float], start: int = 0) -> float:
    """An episode's uncertainty: the maximum score from control step ``start`` on (nan if none)."""
    tail = np.asarray(scores[start:], dtype=np.float64)
    tail = tail[~np.isnan(tail)]
    return float(tail.max()) if tail.size else math.nan


def share_of_maxima_at_end(score_sequences: Sequence[Sequence[float]], end_steps: int) -> float:
    """Share of episodes whose largest score falls in their last ``end_steps`` control steps.

    Over successful nominal episodes it says how often the end of the task, rather than anything
    unusual, raises the score most. NaN scores are ignored; nan when no episode has a score.
    """
    if end_steps < 1:
        raise ValueError(f"`end_steps` must be >= 1. Got {end_steps}.")
    ends = []
    for scores in score_sequences:
        s = np.asarray(scores, dtype=np.float64)
        if np.isnan(s).all():
            continue
        ends.append(int(np.nanargmax(s)) >= s.size - end_steps)
    return float(np.mean(ends)) if ends else math.nan


def auroc_over_common_steps(
    negatives: Sequence[Sequence[float]],
    positives: Sequence[Sequence[float]],
    onsets: Sequence[int | None] | None = None,
) -> float:
    """Episode-level AUROC with each (negative, positive) pair compared over the control steps both lasted.

    Each episode's score is its maximum score over the first ``min(len(negative), len(positive))``
    steps. An episode that runs on (one whose throw never finishes goes to the time limit; a nominal one
    ends when its throw is over) then cannot win on steps the other never reached: this AUROC measures
    what the score says while both episodes are under way. With ``onsets`` (the positives' perturbation onset steps), a pair that
    ends at or before its positive's onset says nothing about the perturbation and is skipped, as is a
    pair whose scores are NaN over all its common steps. nan when no pair is left.
    """
    onsets = [None] * len(positives) if onsets is None else list(onsets)
    if len(onsets) != len(positives):
        raise ValueError(f"Need one onset per positive run. Got {len(onsets)} for {len(positives)} runs.")
    neg = [_running_max(run) for run in negatives if len(run)]
    wins = ties = pairs = 0
    for run, onset in zip(positives, onsets, strict=True):
        if not len(run):
            continue
        p = _running_max(run)
        for n in neg:
            steps = min(len(p), len(n))
            a, b = p[steps - 1], n[steps - 1]
            if (onset is not None and steps <= onset) or math.isnan(a) or math.isnan(b):
                continue
            pairs += 1
            wins += int(a > b)
            ties += int(a == b)
    return float((wins + 0.5 * ties) / pairs) if pairs else math.nan


def _running_max(scores: Sequence[float]) -> np.ndarray:
    """Maximum of the scores up to each step, NaN ignored (NaN until the first finite score)."""
    return np.fmax.accumulate(np.asarray(scores, dtype=np.float64))


def first_alarm_after(alarms: Sequence[bool], onset: int) -> int | None:
    """First control step at or after ``onset`` with an alarm, or None."""
    return next((k for k in range(onset, len(alarms)) if alarms[k]), None)


def detection_delays(episodes: Sequence[tuple[Sequence[bool], int | None]]) -> list[int]:
    """Control steps from onset to the first alarm, for each (alarms, onset) episode that alarmed."""
    delays = []
    for alarms, onset in episodes:
        if onset is None:
            continue
        first = first_alarm_after(alarms, onset)
        if first is not None:
            delays.append(first - onset)
    return delays


def summarize(values: Sequence[float]) -> dict:
    """Median and spread (quartiles, min, max) of a sample; n = 0 gives nulls."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        return {"n": 0, "median": None, "q25": None, "q75": None, "min": None, "max": None}
    return {
        "n": int(v.size),
        "median": float(np.median(v)),
        "q25": float(np.percentile(v, 25)),
        "q75": float(np.percentile(v, 75)),
        "min": float(v.min()),
        "max": float(v.max()),
    }


def failure_prediction_balanced_accuracy(
    first_alarms: Sequence[int | None], failure_steps: Sequence[int | None]
) -> float:
    """Does an alarm come before a failure, and stay away from successes? Balanced accuracy over episodes.

    Per episode, ``first_alarms`` is its first alarmed control step (None: none) and ``failure_steps`` the
    step its failure is known (the episode's last step for a failed episode, None for a success). A failed
    episode counts as predicted when its first alarm comes at or before its failure step; a successful
    one as a false alarm when it alarms at all. Returns (TPR + TNR) / 2, 0.5 for a detector that alarms
    at random, or at always or never; nan when either class is missing (one rate alone would be
    reported as a balanced one).
    """
    if len(first_alarms) != len(failure_steps):
        raise ValueError(
            f"Need one first alarm per episode. Got {len(first_alarms)} for {len(failure_steps)} episodes."
        )
    hits = [
        a is not None and a <= f for a, f in zip(first_alarms, failure_steps, strict=True) if f is not None
    ]
    quiet = [a is None for a, f in zip(first_alarms, failure_steps, strict=True) if f is None]
    if not hits or not quiet:
        return math.nan
    return float(0.5 * (np.mean(hits) + np.mean(quiet)))


def alarm_rates(alarm_sequences: Sequence[Sequence[bool]]) -> dict:
    """Per-step and per-episode false-alarm rates over in-distribution episodes."""
    steps = sum(len(a) for a in alarm_sequences)
    return {
        "per_step": float(sum(sum(a) for a in alarm_sequences) / steps) if steps else math.nan,
        "per_episode": float(np.mean([any(a) for a in alarm_sequences])) if alarm_sequences else math.nan,
        "episodes": len(alarm_sequences),
        "alarmed_episodes": sum(any(a) for a in alarm_sequences),
    }


def insertion_accuracy(
    entry_errors_m: Sequence[float],
    exit_errors_m: Sequence[float],
    entry_tolerance_m: float,
    exit_tolerance_m: float,
) -> dict:
    """Where the needle crossed the tissue surface, over episodes: why insertions fail.

    ``entry_errors_m`` / ``exit_errors_m``: per episode, the distance (m) in the tissue surface from the
    marked point to where the tip crossed it at the episode's end, ``inf`` where it never did. Returns
    the fraction of episodes within each tolerance and the spread of the finite errors in mm.
    """
    entry = np.asarray(entry_errors_m, dtype=np.float64)
    exit_ = np.asarray(exit_errors_m, dtype=np.float64)
    if entry.shape != exit_.shape or entry.ndim != 1:
        raise ValueError(
            f"Need one entry and one exit error per episode. Got shapes {entry.shape} and {exit_.shape}."
        )
    entry_ok, exit_ok = entry <= entry_tolerance_m, exit_ <= exit_tolerance_m

    def share(mask: np.ndarray) -> float:
        return float(np.mean(mask)) if mask.size else math.nan

    return {
        "episodes": entry.size,
        "entry_within_tolerance": share(entry_ok),
        "exit_within_tolerance": share(exit_ok),
        "both_within_tolerance": share(entry_ok & exit_ok),
        "never_entered": int(np.sum(~np.isfinite(entry))),
        "never_emerged": int(np.sum(~np.isfinite(exit_))),
        "entry_error_mm": summarize(1e3 * entry[np.isfinite(entry)]),
        "exit_error_mm": summarize(1e3 * exit_[np.isfinite(exit_)]),
        "entry_tolerance_mm": 1e3 * entry_tolerance_m,
        "exit_tolerance_mm": 1e3 * exit_tolerance_m,
    }


def most_failures_flagged(
    failed_scores: Sequence[float], succeeded_scores: Sequence[float], max_flagged_of_successes: float
) -> float:
    """The largest share of failed runs any threshold flags while flagging at most
    ``max_flagged_of_successes`` of the successful ones (a run is flagged when its score exceeds the
    threshold; scores are per-run maxima). A hindsight bound: no calibration of this score can do better.
    nan when either side is empty."""
    if not 0 <= max_flagged_of_successes <= 1:
        raise ValueError(f"`max_flagged_of_successes` must lie in [0, 1]. Got {max_flagged_of_successes}.")
    failed = np.asarray(failed_scores, dtype=np.float64)
    succeeded = np.sort(np.asarray(succeeded_scores, dtype=np.float64))[::-1]
    if failed.size == 0 or succeeded.size == 0:
        return math.nan
    allowed = int(math.floor(max_flagged_of_successes * succeeded.size + 1e-9))
    if allowed >= succeeded.size:
        return 1.0
    # The lowest threshold that lets through at most `allowed` successes: the next success's own score.
    return float(np.mean(failed > succeeded[allowed]))
