"""Tracking error: did the instrument arrive where the policy sent it?

Every detector of the image-policy field reads the policy (its samples, its features); none reads what
the arm did with the last command. Industrial arms detect collisions from that gap between the
commanded and the measured motion (Haddadin, De Luca and Albu-Schaeffer, IEEE T-RO 2017); here it is
model-free. When a prediction is made ``shift`` control steps after the previous one, the jaw should sit
at the target of the last executed step of the previous chunk, the executed mean over all members and
samples:

    x_hat = mean_{n,k} x_{n,k,t}  of the previous prediction,   t = action_start + shift - 1.

The state the policy now reads, s, is compared with it. State and action are normalized by different
statistics (one jaw pose, two affine scalings), so the detector fits, per dimension on nominal predictions,
s ~= a x_hat + b by least squares, and standardizes the residual by its nominal spread sd:

    score = sqrt(mean_i ((s_i - a_i x_hat_i - b_i) / sd_i)^2)    over the jaw position (``dims``).

What lies between the command and the measurement raises it: a command executed late, a noisy reading of
the jaw's position, a force that drags the instrument (tissue that moved with the needle in it). What the
policy commands wrongly but the arm executes faithfully does not. The first prediction of an episode has
no previous command to compare with and scores 0. The state and the action must share one layout (the
suture env's ``agent_pos`` is the jaw pose in the action's layout).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from lerobot_suture.detectors.base import PredictionFeatures, require

POSITION_DIMS = (0, 1, 2)
"""The jaw tip's position in the action and state layout (the tip-first controller tracks it first)."""


def commanded_target(previous_samples: np.ndarray, action_start: int, shift: int) -> np.ndarray:
    """The executed target of the last control step before the new prediction: (A,) from the previous
    prediction's (N, K, T, A) samples, ``shift`` >= 1 steps after it."""
    previous_samples = np.asarray(previous_samples, dtype=np.float64)
    t = action_start + shift - 1
    if not (1 <= shift and t < previous_samples.shape[-2]):
        raise ValueError(
            f"A prediction {shift} steps after the previous one falls outside its chunk of "
            f"{previous_samples.shape[-2]} steps (first executed step {action_start})."
        )
    return previous_samples[..., t, :].reshape(-1, previous_samples.shape[-1]).mean(axis=0)


@dataclass(frozen=True)
class TrackingFit:
    """Per dimension: the affine map from commanded target to state (a, b) and the residual's spread."""

    slope: np.ndarray  # (D,)
    intercept: np.ndarray  # (D,)
    scale: np.ndarray  # (D,)


def fit_tracking(targets: np.ndarray, states: np.ndarray) -> TrackingFit:
    """Least-squares s ~= a x_hat + b per dimension over nominal pairs, targets and states (M, D), M >= 3."""
    x, s = np.asarray(targets, dtype=np.float64), np.asarray(states, dtype=np.float64)
    if x.ndim != 2 or x.shape != s.shape or x.shape[0] < 3:
        raise ValueError(
            f"Tracking needs (M, D) targets and states of one shape with M >= 3. Got {x.shape} and {s.shape}."
        )
    xc, sc = x - x.mean(axis=0), s - s.mean(axis=0)
    var = (xc**2).sum(axis=0)
    slope = np.where(var > 0, (xc * sc).sum(axis=0) / np.where(var > 0, var, 1.0), 1.0)
    intercept = s.mean(axis=0) - slope * x.mean(axis=0)
    scale = (s - slope * x - intercept).std(axis=0)
    return TrackingFit(slope, intercept, np.where(scale > 0, scale, 1.0))


def tracking_score(fit: TrackingFit, target: np.ndarray, state: np.ndarray) -> float:
    """RMS over the fitted dimensions of the standardized residual of ``state`` against ``target`` (D,)."""
    z = (np.asarray(state, dtype=np.float64) - fit.slope * target - fit.intercept) / fit.scale
    return float(np.sqrt(np.mean(z**2)))


def _pair(features: PredictionFeatures, name: str, dims: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    state = require(features.state, name, "the state each prediction was made from")
    target = commanded_target(features.previous_samples, features.action_start, features.shift)
    if state.shape[-1] != target.shape[-1]:
        raise ValueError(
            f"Detector {name!r} compares the state with the commanded action, which must share one layout. "
            f"Got a state of {state.shape[-1]} and an action of {target.shape[-1]} dimensions."
        )
    return target[list(dims)], np.asarray(state, dtype=np.float64)[list(dims)]


@dataclass
class TrackingErrorDetector:
    """Standardized gap between the jaw position the policy commanded and the one it then reads."""

    name: str = "tracking_error"
    dims: tuple[int, ...] = POSITION_DIMS
    fitted: TrackingFit | None = field(default=None, repr=False)

    def fit(self, features: Sequence[PredictionFeatures]) -> TrackingErrorDetector:
        pairs = [_pair(f, self.name, self.dims) for f in features if f.previous_samples is not None]
        if len(pairs) < 3:
            raise ValueError(
                f"Detector {self.name!r} fits on consecutive predictions; got {len(pairs)} with a previous one."
            )
        targets, states = (np.stack(p) for p in zip(*pairs, strict=True))
        self.fitted = fit_tracking(targets, states)
        return self

    def score(self, features: PredictionFeatures) -> float:
        if self.fitted is None:
            raise ValueError(f"Detector {self.name!r} is not fitted; call `fit` on nominal predictions.")
        if features.previous_samples is None:
            return 0.0  # the episode's first prediction: no command yet
        return tracking_score(self.fitted, *_pair(features, self.name, self.dims))
