"""Failure detectors compared on the same rollouts (``lerobot-suture benchmark-ood``).

Each detector is a small class behind :class:`~lerobot_suture.detectors.base.Detector` (``fit`` on nominal
predictions, ``score`` one prediction) over pure functions in its own module.
"""

from lerobot_suture.detectors.aleatoric import SingleMemberSpreadDetector
from lerobot_suture.detectors.base import Detector, PredictionFeatures, timed_scores
from lerobot_suture.detectors.covariance import EnsembleCovarianceDetector, EpistemicDetector
from lerobot_suture.detectors.mahalanobis import MahalanobisDetector
from lerobot_suture.detectors.rnd import RNDDetector
from lerobot_suture.detectors.stac import TemporalConsistencyDetector
from lerobot_suture.detectors.tracking import TrackingErrorDetector

__all__ = [
    "DETECTOR_NAMES",
    "Detector",
    "EnsembleCovarianceDetector",
    "EpistemicDetector",
    "MahalanobisDetector",
    "PredictionFeatures",
    "RNDDetector",
    "SingleMemberSpreadDetector",
    "TemporalConsistencyDetector",
    "TrackingErrorDetector",
    "make_detector",
    "timed_scores",
]

_DETECTORS = {
    "ensemble_covariance": EnsembleCovarianceDetector,
    "single_member_spread": SingleMemberSpreadDetector,
    "mahalanobis": MahalanobisDetector,
    "stac": TemporalConsistencyDetector,
    "rnd": RNDDetector,
    "epistemic": EpistemicDetector,
    "tracking_error": TrackingErrorDetector,
}
DETECTOR_NAMES = tuple(_DETECTORS)
"""Every detector, the paper's (and the gate's) score first."""


def make_detector(name: str) -> Detector:
    """A fresh detector by name (one of :data:`DETECTOR_NAMES`)."""
    if name not in _DETECTORS:
        raise ValueError(f"Unknown detector {name!r}. Choose among {list(DETECTOR_NAMES)}.")
    return _DETECTORS[name]()
