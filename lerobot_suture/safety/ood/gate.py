"""The O.O.D. gate a policy holds: the likelihood-ratio test on each prediction, latched per episode."""

import math
from dataclasses import dataclass, field

import numpy as np

from lerobot_suture.safety.ood.calibration import CALIBRATE_HINT, CalibrationMode, OODCalibration
from lerobot_suture.safety.ood.likelihood_ratio import likelihood_ratio_test, standardized_score

__all__ = ["OODGate", "silent_status"]


def silent_status() -> dict:
    """The status of a gate that has not scored anything (no prediction yet, or no gate at all): NaN score
    and threshold, no O.O.D. decision, control not released (the keys of ``ood_status``)."""
    return {
        "score": math.nan,
        "threshold": math.nan,
        "decision": False,
        "released": False,
        "new_prediction": False,
    }


@dataclass
class OODGate:
    """Stateful O.O.D. gate for one episode at a time, to be held by a policy.

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
        calibration: The fitted calibration, or None to only record scores.
        enforce: Whether the policy should act on ``released`` (see above).

    Attributes:
        last_score: Score of the latest update (NaN before the first).
        running_max: Maximum score since :meth:`reset` (-inf before the first; NaN scores are skipped).
        last_statistic: Standardized statistic z of the tested value (score or running max) of the latest
            update (NaN before the first or without calibration).
        decision: Test decision of the latest update: per prediction, ``last_score > threshold``; per
            episode, ``running_max > threshold``. NaN scores decide O.O.D.
        released: True from the first O.O.D. decision until :meth:`reset`.
        n_updates: Number of updates since :meth:`reset`.
        released_at: Index (0-based, since reset) of the update that released control, or None.
    """

    calibration: OODCalibration | None = None
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
