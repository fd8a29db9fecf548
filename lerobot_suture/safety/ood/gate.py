"""The one O.O.D. gate: a detector's score of each predicted chunk, tested against a conformal calibration,
latched per episode.

Every path holds this gate. The ensemble's policy feeds it its members' covariance score (one gate per env
of the batch); any other chunking policy feeds it STAC's score of each chunk against the one before
(:class:`ChunkGate` over :class:`~lerobot_suture.safety.ood.chunk_consistency.ChunkConsistencyMonitor`), on the
env path and on the robot path alike. The decision is taken per chunk, when it is predicted and before any of its
actions is executed, so an inference thread that reads it can keep a flagged chunk off the arm.

- the detector: anything with ``reset()`` and ``score(chunk) -> float`` (:class:`ChunkDetector`); higher is less
  like the calibration's rollouts;
- the calibration: anything with a ``threshold`` and a ``mode`` (:class:`GateCalibration`): the ensemble's
  :class:`~lerobot_suture.safety.ood.calibration.OODCalibration` or STAC's
  :class:`~lerobot_suture.safety.ood.calibration_file.StacCalibration`. STAC's, and the ensemble's in its default
  per-episode mode, are the split-conformal quantile of nominal episodes' maxima
  (:func:`~lerobot_suture.safety.ood.calibration.conformal_episode_threshold`);
- the decision: :class:`OODGate`, ``score > threshold`` (on the episode's running maximum per episode), a NaN
  score failing safe, latched from the first O.O.D. decision until ``reset``.
"""

import math
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from lerobot_suture.safety.ood.calibration import CALIBRATE_HINT, CalibrationMode, OODCalibration
from lerobot_suture.safety.ood.likelihood_ratio import likelihood_ratio_test, standardized_score

__all__ = ["ChunkDetector", "ChunkGate", "GateCalibration", "OODGate", "silent_status"]


@runtime_checkable
class GateCalibration(Protocol):
    """What the gate tests a score against: ``threshold`` (score units) and ``mode`` (``per_prediction``: each
    score; ``per_episode``: the episode's running maximum)."""

    threshold: float
    mode: str


@runtime_checkable
class ChunkDetector(Protocol):
    """A detector that scores each predicted chunk of one episode (it may remember the chunks before)."""

    def reset(self) -> None:
        """A new episode: forget the chunks before."""
        ...

    def score(self, chunk: np.ndarray) -> float:
        """The new chunk's score, higher meaning less like nominal."""
        ...


def silent_status() -> dict:
    """The status of a gate that has not scored anything (no prediction yet, or no gate at all): NaN score
    and threshold, no O.O.D. decision, control not released (the keys of ``ood_status``)."""
    return {
        "score": math.nan,
        "threshold": math.nan,
        "decision": False,
        "released": False,
        "flagged": False,
        "new_prediction": False,
    }


@dataclass
class OODGate:
    """The latched O.O.D. decision for one episode at a time.

    Call :meth:`update` with each prediction's score; it returns the current test decision. Once a
    decision is O.O.D. the gate is ``released`` (latched) until :meth:`reset`, which the policy calls at
    the start of every episode.

    ``enforce`` is carried for the policy and does not change what the gate computes: with
    ``enforce=False`` the policy only reports ``last_score``, ``threshold`` and ``decision`` (the paper's
    experiments); with ``enforce=True`` the policy stops commanding motion (it holds the current pose)
    while ``released`` is True, handing control to the surgeon. Enforcing needs a calibration; without one
    (allowed only with ``enforce=False``, e.g. while recording calibration rollouts) the gate records
    scores and never decides O.O.D.

    Args:
        calibration: The fitted calibration (:class:`GateCalibration`), or None to only record scores.
        enforce: Whether the policy should act on ``released`` (see above).

    Attributes:
        last_score: Score of the latest update (NaN before the first).
        running_max: Maximum score since :meth:`reset` (-inf before the first; NaN scores are skipped).
        last_statistic: Standardized statistic z of the tested value (score or running max) of the latest
            update (NaN before the first, without calibration, or for a calibration without an I.D. model).
        decision: Test decision of the latest update: per prediction, ``last_score > threshold``; per
            episode, ``running_max > threshold``. NaN scores decide O.O.D.
        released: True from the first O.O.D. decision until :meth:`reset`.
        n_updates: Number of updates since :meth:`reset`.
        released_at: Index (0-based, since reset) of the update that released control, or None.
    """

    calibration: GateCalibration | None = None
    enforce: bool = False
    last_score: float = field(default=math.nan, init=False)
    running_max: float = field(default=-math.inf, init=False)
    last_statistic: float = field(default=math.nan, init=False)
    decision: bool = field(default=False, init=False)
    released: bool = field(default=False, init=False)
    n_updates: int = field(default=0, init=False)
    released_at: int | None = field(default=None, init=False)

    def __post_init__(self):
        if self.enforce and self.calibration is None:
            raise ValueError(f"An enforced OOD gate needs a calibration. {CALIBRATE_HINT}")

    @property
    def threshold(self) -> float:
        """Score threshold of the test (NaN without calibration)."""
        return math.nan if self.calibration is None else self.calibration.threshold

    @property
    def mode(self) -> str | None:
        """Calibration mode, or None without calibration."""
        return None if self.calibration is None else self.calibration.mode

    def update(self, score: float) -> bool:
        """Record one prediction's score and return the test decision (True = O.O.D.).

        Args:
            score: The prediction's uncertainty score (a scalar, e.g. from :func:`compute_score`).

        Returns:
            The decision of this update; see ``decision`` and ``released``.
        """
        score = float(np.asarray(score, dtype=np.float64).reshape(()))
        self.last_score = score
        if not math.isnan(score):
            self.running_max = max(self.running_max, score)
        if self.calibration is None:
            self.decision = False
        else:
            per_episode = self.calibration.mode == CalibrationMode.PER_EPISODE
            tested = score if math.isnan(score) or not per_episode else self.running_max
            self.decision = likelihood_ratio_test(tested, self.calibration)
            if isinstance(self.calibration, OODCalibration):
                self.last_statistic = standardized_score(tested, self.calibration)
        if self.decision and not self.released:
            self.released = True
            self.released_at = self.n_updates
        self.n_updates += 1
        return self.decision

    def reset(self) -> None:
        """Start a new episode: clear the scores, the decision and the latch (calibration is kept)."""
        self.last_score = math.nan
        self.running_max = -math.inf
        self.last_statistic = math.nan
        self.decision = False
        self.released = False
        self.n_updates = 0
        self.released_at = None


class ChunkGate:
    """A :class:`ChunkDetector` and the :class:`OODGate` its scores feed: ``update(chunk)`` scores a new chunk and
    returns whether the episode is flagged (latched).

    Args:
        detector: scores each chunk.
        calibration: the detector's calibration, or None to record scores only (while calibrating).
    """

    def __init__(self, detector: ChunkDetector, calibration: GateCalibration | None = None):
        if not isinstance(detector, ChunkDetector):
            raise TypeError(
                f"{type(detector).__name__} is not a chunk detector: it needs `reset()` and `score(chunk)`."
            )
        self.detector = detector
        self.gate = OODGate(calibration=calibration)
        self.scores: list[float] = []

    def reset(self) -> None:
        """A new episode."""
        self.detector.reset()
        self.gate.reset()
        self.scores = []

    def update(self, chunk: np.ndarray) -> bool:
        score = float(self.detector.score(chunk))
        self.scores.append(score)
        self.gate.update(score)
        return self.gate.released

    @property
    def flagged(self) -> bool:
        return self.gate.released
