"""A gate for each stage of a long task: the one gate (:class:`~lerobot_suture.safety.ood.gate.OODGate`) per
segment, with a threshold per subtask.

A running suture is about twelve segments (four throws of insert, extract, lay down, pick up; the high level of
:mod:`lerobot_suture.sim.subtasks` names them from the measured pose). One threshold for the whole suture would be
set by its noisiest stage; a threshold per subtask holds each stage to its own nominal spread. Following
FAIL-Detect, each subtask's threshold is the split-conformal quantile of the largest score of that subtask's
segments in successful rollouts (:func:`fit_stage_thresholds`), so a policy's failures are never taken for
normal. A per-suture false-alarm rate of 10% over twelve segments needs about 1% per segment, and the quantile
at 1% needs at least 99 successful segments of each subtask (:func:`~lerobot_suture.safety.ood.calibration.min_calibration_episodes`).

:class:`StageGate` tests each segment's running maximum against its subtask's threshold and latches the first
flag with the segment it fell in, so a surgeon can take that segment over and hand back for the next.

A stage can also fail without a surprising score: a policy that closes its jaw beside the needle and never opens
it again stalls in its extract, every prediction in distribution. A time budget per subtask
(:class:`StageBudgets`) flags a segment that runs longer than the same conformal quantile of successful segments'
durations (:func:`fit_stage_budgets`): the number of control steps is the score, and its maximum is the segment's
length.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from lerobot_suture.safety.ood.calibration import (
    CalibrationMode,
    conformal_episode_threshold,
    min_calibration_episodes,
)
from lerobot_suture.safety.ood.gate import OODGate

STAGE_CALIBRATION_FILE = "stage_calibration.json"
STAGE_BUDGETS_FILE = "stage_budgets.json"


@dataclass(frozen=True)
class SegmentThreshold:
    """One subtask's threshold on its segments' running maximum (a :class:`~.gate.GateCalibration`)."""

    threshold: float
    mode: str = CalibrationMode.PER_EPISODE.value


class _FittedPerSubtask:
    """What :class:`StageThresholds` and :class:`StageBudgets` share: a per-segment false-alarm rate ``alpha`` in
    (0, 0.5), and a JSON file of their own in a policy's directory (``FILE``; ``MISSING`` says how to fit one)."""

    FILE: ClassVar[str]
    MISSING: ClassVar[str]

    def _check_alpha(self) -> None:
        if not 0 < self.alpha < 0.5:
            raise ValueError(f"`alpha` must be in (0, 0.5). Got {self.alpha!r}.")

    def save(self, directory: str | os.PathLike) -> Path:
        path = Path(directory) / self.FILE
        path.write_text(json.dumps(asdict(self), indent=2) + "\n")
        return path

    @classmethod
    def load(cls, directory: str | os.PathLike):
        path = Path(directory) / cls.FILE
        if not path.is_file():
            raise FileNotFoundError(cls.MISSING.format(path=path))
        return cls(**json.loads(path.read_text()))


def _check_enough_segments(counts: dict[str, int], alpha: float, what: str, advice: str) -> None:
    """Refuse to fit ``what`` at ``alpha`` unless every subtask of ``counts`` (subtask -> successful segments) has as
    many as the conformal quantile needs; ``advice`` says how to get more."""
    needed = min_calibration_episodes(alpha)
    short = {stage: n for stage, n in counts.items() if n < needed}
    if short or not counts:
        raise ValueError(
            f"A {what} at alpha={alpha} needs at least {needed} successful segments per subtask. Got {short or 'none'}; "
            f"{advice}."
        )


@dataclass(frozen=True)
class StageThresholds(_FittedPerSubtask):
    """Each subtask's threshold, fitted on successful segments.

    Args:
        thresholds: subtask -> threshold on a segment's largest score.
        segments: subtask -> successful segments it was fitted on.
        alpha: the per-segment false-alarm rate it was fitted for, in (0, 0.5).
    """

    thresholds: dict[str, float]
    segments: dict[str, int]
    alpha: float
    FILE: ClassVar[str] = STAGE_CALIBRATION_FILE
    MISSING: ClassVar[str] = "No stage calibration at {path}: fit one with `fit_stage_thresholds`."

    def __post_init__(self):
        self._check_alpha()
        bad = {s: t for s, t in self.thresholds.items() if not math.isfinite(t)}
        if bad:
            raise ValueError(f"Every threshold must be finite. Got {bad}.")


@dataclass(frozen=True)
class StageBudgets(_FittedPerSubtask):
    """Each subtask's time budget, fitted on the durations of successful segments.

    Args:
        budgets: subtask -> the control steps a segment may run; one step more flags it.
        segments: subtask -> successful segments it was fitted on.
        alpha: the per-segment false-alarm rate it was fitted for, in (0, 0.5).
        source: where the segments came from (a dataset's path, the policy's rollouts).
    """

    budgets: dict[str, int]
    segments: dict[str, int]
    alpha: float
    source: str = ""
    FILE: ClassVar[str] = STAGE_BUDGETS_FILE
    MISSING: ClassVar[str] = "No stage budgets at {path}: fit them with `fit_stage_budgets`."

    def __post_init__(self):
        self._check_alpha()
        bad = {s: b for s, b in self.budgets.items() if not (isinstance(b, int) and b >= 1)}
        if bad:
            raise ValueError(f"Every budget must be a whole number of control steps >= 1. Got {bad}.")


def fit_stage_budgets(
    durations: dict[str, Sequence[int]], alpha: float = 0.01, source: str = ""
) -> StageBudgets:
    """Each subtask's budget: the split-conformal quantile at ``alpha`` of its successful segments' durations
    (control steps), rounded up.

    Raises:
        ValueError: a subtask has fewer segments than the quantile at ``alpha`` needs, or a duration < 1.
    """
    _check_enough_segments(
        {stage: len(values) for stage, values in durations.items()},
        alpha,
        "budget",
        "record more sutures or raise alpha",
    )
    if any(int(d) < 1 for values in durations.values() for d in values):
        raise ValueError("Every segment lasts at least one control step.")
    return StageBudgets(
        budgets={
            stage: math.ceil(conformal_episode_threshold(np.asarray(values, dtype=np.float64), alpha))
            for stage, values in durations.items()
        },
        segments={stage: len(values) for stage, values in durations.items()},
        alpha=float(alpha),
        source=source,
    )


def segment_runs(subtasks: Sequence[str]) -> list[tuple[str, int, int, int]]:
    """The segments of one episode's per-step subtasks: (subtask, throw, start, stop) with ``stop`` exclusive; the
    throw counts the insert segments begun so far (0-based; 0 before the first)."""
    runs, throw = [], -1
    for step, subtask in enumerate(subtasks):
        if not runs or subtask != runs[-1][0]:
            throw += subtask == "insert"
            runs.append([subtask, max(throw, 0), step, step + 1])
        else:
            runs[-1][3] = step + 1
    return [tuple(run) for run in runs]


def segment_maxima(
    scores: Sequence[float], stages: Sequence[str], segments: Sequence[int], successful: Sequence[bool]
) -> dict[str, np.ndarray]:
    """Per subtask, the largest score of each successful segment.

    Args:
        scores: (N,) one score per prediction.
        stages: (N,) the subtask each prediction was made in.
        segments: (N,) the segment (an id unique over all rollouts) each prediction belongs to.
        successful: (N,) whether that prediction's segment succeeded (FAIL-Detect keeps only those).
    """
    scores = np.asarray(scores, dtype=np.float64)
    if not (len(scores) == len(stages) == len(segments) == len(successful)):
        raise ValueError(
            "`scores`, `stages`, `segments` and `successful` must have one entry per prediction."
        )
    maxima: dict[tuple[str, int], float] = {}
    for score, stage, segment, ok in zip(scores, stages, segments, successful, strict=True):
        if ok:
            key = (str(stage), int(segment))
            maxima[key] = max(maxima.get(key, -math.inf), float(score))
    found: dict[str, list[float]] = {}
    for (stage, _), value in maxima.items():
        found.setdefault(stage, []).append(value)
    return {stage: np.asarray(values) for stage, values in found.items()}


def fit_stage_thresholds(
    scores: Sequence[float],
    stages: Sequence[str],
    segments: Sequence[int],
    successful: Sequence[bool],
    alpha: float = 0.01,
) -> StageThresholds:
    """Each subtask's threshold: the split-conformal quantile of its successful segments' maxima at ``alpha``.

    Raises:
        ValueError: a subtask has fewer successful segments than the quantile at ``alpha`` needs (the message
            names it and how many it needs).
    """
    maxima = segment_maxima(scores, stages, segments, successful)
    _check_enough_segments(
        {stage: len(values) for stage, values in maxima.items()},
        alpha,
        "threshold",
        "roll out more (successful) episodes or raise alpha",
    )
    return StageThresholds(
        thresholds={stage: conformal_episode_threshold(values, alpha) for stage, values in maxima.items()},
        segments={stage: len(values) for stage, values in maxima.items()},
        alpha=float(alpha),
    )


class StageGate:
    """The one gate per segment: a new segment (subtask or throw changed) starts a fresh running maximum, tested
    against its subtask's threshold. Every flag is kept in ``flags`` (a surgeon takes that segment over and hands
    back for the next, whose gate starts afresh). A hand-back inside the flagged segment (:meth:`rearm`: the
    surgeon's part of the subtask is done while the high level still reads it) starts its gate and its budget
    afresh too, so the policy is not flagged again at once for the steps the surgeon took.

    Args:
        thresholds: the fitted :class:`StageThresholds`, or None to record scores only (while calibrating); a
            subtask without a threshold is never flagged on its scores.
        budgets: the fitted :class:`StageBudgets`, or None: a segment that outlasts its subtask's budget
            (:meth:`tick` once per control step) is flagged too.
    """

    def __init__(self, thresholds: StageThresholds | None, budgets: StageBudgets | None = None):
        self.thresholds, self.budgets = thresholds, budgets
        self.reset()

    def reset(self) -> None:
        """A new rollout."""
        self.segment: tuple[str, int] | None = None
        self.flags: list[tuple[str, int]] = []
        self.gate = OODGate()
        self.steps = 0
        """Control steps of the current segment so far (since the last hand-back in it)."""
        self._flagged = False

    def threshold(self, subtask: str) -> float:
        """``subtask``'s threshold (NaN without one)."""
        found = None if self.thresholds is None else self.thresholds.thresholds.get(subtask)
        return math.nan if found is None else found

    def enter(self, subtask: str, throw: int) -> None:
        """The arm is in ``subtask`` of ``throw`` (the high level's reading); a new segment re-arms the gate."""
        segment = (subtask, int(throw))
        if segment != self.segment:
            self.segment = segment
            self.rearm()

    def rearm(self) -> None:
        """A fresh gate and time budget for the current segment (a new one, or a hand-back inside it); its flags
        so far stay in ``flags``."""
        threshold = math.nan if self.segment is None else self.threshold(self.segment[0])
        self.gate = OODGate(calibration=None if math.isnan(threshold) else SegmentThreshold(threshold))
        self.steps, self._flagged = 0, False

    def _flag(self) -> None:
        if not self._flagged:
            self.flags.append(self.segment)
            self._flagged = True

    def tick(self) -> bool:
        """One control step of the current segment; returns whether the segment is flagged (over its budget now,
        or before)."""
        if self.segment is None:
            raise RuntimeError("`enter` a segment before its first step.")
        self.steps += 1
        budget = None if self.budgets is None else self.budgets.budgets.get(self.segment[0])
        if budget is not None and self.steps > budget:
            self._flag()
        return self.flagged_here

    def update(self, score: float) -> bool:
        """One prediction's score in the current segment; returns whether this segment is flagged."""
        if self.segment is None:
            raise RuntimeError("`enter` a segment before its first score.")
        if self.gate.update(score):
            self._flag()
        return self.flagged_here

    @property
    def flagged_here(self) -> bool:
        """The current segment is flagged (since it began, or since the last hand-back in it)."""
        return self._flagged
