"""The O.O.D. gate on the robot path, for the policy ``lerobot-rollout`` loaded, and the endoscope's health.

- ``ensemble``: an ``ensemble_diffusion`` policy with a calibration reads its own gate (its members'
  covariance, calibrated per episode: ``lerobot-suture calibrate``) after every prediction, ``policy.ood_status()``.
- ``stac``: any other policy that predicts chunks (ACT, diffusion, ...): the temporal consistency of its
  successive chunks, tested against ``stac_calibration.json`` beside the policy
  (:mod:`lerobot_suture.safety.ood.chunk_consistency`; ``lerobot-suture calibrate-stac``).
- the camera watchdog (:mod:`lerobot_suture.safety.camera_watchdog`), on either: a frozen or dropped endoscope
  frame while the arm moves flags too. A frozen frame is an in-distribution image, so no score on the image
  alone sees it.

:class:`RolloutGate` ``.read(observation)``, once the policy has predicted its action and before the action is
sent, gives a :class:`GateReading`. The score's gate is the env path's (:func:`~lerobot_suture.runtime.gates.policy_gates`:
the one latched :class:`~lerobot_suture.safety.ood.gate.OODGate`); the camera watchdog latches its own flag.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lerobot_suture.runtime.gates import GATE_KINDS, policy_gates
from lerobot_suture.safety.camera_watchdog import CameraWatchdog, CameraWatchdogConfig

from .config_suture_sim import CAMERA, POSE_FEATURES

__all__ = ["GATE_KINDS", "GateReading", "RolloutGate"]


@dataclass(frozen=True)
class GateReading:
    """The gate after one action.

    Attributes:
        score: the last prediction's score (the ensemble's uncertainty, or STAC's squared MMD); NaN before any.
        threshold: the calibrated threshold the score is tested against (NaN without one).
        decision: out of distribution (the score's test, or the camera flagged); latched for the episode.
        camera_stale: the camera watchdog has flagged the endoscope this episode.
        new_prediction: the policy predicted a new chunk for this action.
    """

    score: float
    threshold: float
    decision: bool
    camera_stale: bool
    new_prediction: bool


class RolloutGate:
    """The gate for ``policy`` (see the module docstring).

    Args:
        policy: the loaded LeRobot policy.
        kind: ``auto`` (``ensemble`` for a calibrated ensemble, else ``stac`` when a STAC calibration is found,
            else only the camera watchdog), ``ensemble``, ``stac`` or ``none`` (the camera watchdog only).
        policy_dir: where the policy was loaded from (its ``stac_calibration.json``).
        camera: the camera watchdog's configuration, or None to leave the camera unwatched.

    Raises:
        ValueError: an unknown ``kind``, or ``ensemble`` for a policy without a calibrated gate.
        FileNotFoundError: ``stac`` without a STAC calibration (the message says how to make one).
    """

    def __init__(
        self,
        policy,
        kind: str = "auto",
        policy_dir: str | Path | None = None,
        camera: CameraWatchdogConfig | None = None,
    ):
        self.policy = policy
        self._gates = policy_gates(policy, kind, policy_dir)
        self.kind = self._gates.kind
        self._watchdog = CameraWatchdog(camera) if camera is not None else None
        self.reset()

    def reset(self) -> None:
        """A new episode: STAC's gate and previous chunk, and the watchdog, are forgotten (the ensemble's policy
        resets its own gate)."""
        self._gates.reset(1)
        if self._watchdog is not None:
            self._watchdog.reset()

    def close(self) -> None:
        self._gates.close()

    def read(self, observation: dict) -> GateReading:
        """The gate once the policy has predicted its action for ``observation`` (the robot's raw observation),
        before that action is sent. STAC assumes one policy call per control step (synchronous inference)."""
        if self._watchdog is not None and CAMERA in observation:
            pose = np.array([float(observation[k]) for k in POSE_FEATURES])
            self._watchdog.update(np.asarray(observation[CAMERA]), pose)
        stale = self._watchdog is not None and self._watchdog.flagged
        status = self._gates.status(0)
        return GateReading(
            float(status["score"]),
            float(status["threshold"]),
            bool(status["flagged"]) or stale,
            stale,
            bool(status["new_prediction"]),
        )
