"""What a failure detector reads from one prediction, the interface every detector has, and its cost.

A detector is fitted once on nominal predictions (:meth:`Detector.fit`) and then maps each new
prediction to one score (:meth:`Detector.score`), higher meaning less like the nominal data. The score is
held between predictions, as the policy's own gate holds it, and thresholded per episode by
:func:`~lerobot_suture.safety.ood.calibration.conformal_episode_threshold`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class PredictionFeatures:
    """One prediction of one env, as detectors read it (all actions in the policy's normalized space).

    Attributes:
        samples: (N, K, T, A) every member's K sampled chunks over the T predicted steps.
        action_start: index in T of the first executed step (``n_obs_steps - 1``).
        embedding: (N, G) each member's observation embedding (state and image features), or None when
            the policy was not asked to capture it.
        single_member_samples: (K', T, A) further chunks of member 0 alone, or None.
        previous_samples: (N, K, T, A) the same episode's previous prediction, None at its first.
        shift: control steps between the previous prediction and this one (None at the first).
        state: (S,) the robot state the prediction was made from (its last observation step, normalized as
            the members read it), or None.
    """

    samples: np.ndarray
    action_start: int
    embedding: np.ndarray | None = None
    single_member_samples: np.ndarray | None = None
    previous_samples: np.ndarray | None = None
    shift: int | None = None
    state: np.ndarray | None = None


@runtime_checkable
class Detector(Protocol):
    """A failure detector: ``fit`` on nominal predictions, then ``score`` one prediction at a time."""

    name: str

    def fit(self, features: Sequence[PredictionFeatures]) -> Detector:
        """Learn what nominal looks like (a no-op for detectors with nothing to learn); returns self."""
        ...

    def score(self, features: PredictionFeatures) -> float:
        """One prediction's score: higher is less nominal."""
        ...


def timed_scores(detector: Detector, features: Sequence[PredictionFeatures]) -> tuple[np.ndarray, float]:
    """``detector``'s score of each prediction, (P,), and its mean wall time per call in seconds."""
    scores = np.empty(len(features))
    start = time.perf_counter()
    for i, f in enumerate(features):
        scores[i] = detector.score(f)
    seconds = time.perf_counter() - start
    return scores, seconds / max(len(features), 1)


def require(value: np.ndarray | None, detector: str, what: str) -> np.ndarray:
    """``value``, or a ValueError saying that ``detector`` needs ``what`` captured at inference."""
    if value is None:
        raise ValueError(
            f"Detector {detector!r} needs {what}; capture it with the policy's `enable_feature_capture`."
        )
    return value
