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
sent, gives a :class:`GateReading`; the decision is latched for the episode, as the ensemble's gate releases
control once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lerobot_suture.safety.camera_watchdog import CameraWatchdog, CameraWatchdogConfig
from lerobot_suture.safety.ood.chunk_consistency import (
    STAC_CALIBRATION_FILE,
    ChunkCapture,
    ChunkConsistencyMonitor,
    StacCalibration,
    chunk_source,
)

from .config_suture_sim import CAMERA, POSE_FEATURES

GATE_KINDS = ("auto", "ensemble", "stac", "none")


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
        if kind not in GATE_KINDS:
            raise ValueError(f"`gate` must be one of {GATE_KINDS}. Got {kind!r}.")
        self.policy = policy
        ensemble = callable(getattr(policy, "ood_status", None)) and getattr(policy, "ood_calibration", None)
        if kind == "auto":
            has_stac = policy_dir is not None and (Path(policy_dir) / STAC_CALIBRATION_FILE).is_file()
            kind = "ensemble" if ensemble else "stac" if has_stac else "none"
        if kind == "ensemble" and not ensemble:
            raise ValueError(
                "`gate=ensemble` needs an ensemble_diffusion policy with a calibrated gate: run "
                "`lerobot-suture calibrate --policy.path=DIR` first, or use `gate=stac` for other policies."
            )
        self.kind = kind
        self._capture = self._monitor = self._calibration = None
        if kind == "stac":
            if policy_dir is None:
                raise FileNotFoundError(
                    f"`gate=stac` needs the policy's directory to read {STAC_CALIBRATION_FILE}."
                )
            self._calibration = StacCalibration.load(policy_dir)
            owner, name, start = chunk_source(policy)
            self._capture = ChunkCapture(owner, name)
            shift = int(getattr(policy.config, "n_action_steps", self._calibration.n_action_steps))
            if shift != self._calibration.n_action_steps:
                raise ValueError(
                    f"The STAC calibration in {policy_dir} was fitted with n_action_steps="
                    f"{self._calibration.n_action_steps}; the policy runs {shift}, so successive chunks overlap "
                    "differently. Run `lerobot-suture calibrate-stac` again with these settings."
                )
            self._monitor = ChunkConsistencyMonitor(shift, start, self._calibration.bandwidth)
        self._watchdog = CameraWatchdog(camera) if camera is not None else None
        self.reset()

    def reset(self) -> None:
        """A new episode: the latched decision, the watchdog and STAC's previous chunk are forgotten."""
        self._latched = False
        self._score = math.nan
        self._chunks = self._capture.chunks if self._capture is not None else 0
        if self._monitor is not None:
            self._monitor.reset()
        if self._watchdog is not None:
            self._watchdog.reset()

    def close(self) -> None:
        if self._capture is not None:
            self._capture.release()

    def read(self, observation: dict) -> GateReading:
        """The gate once the policy has predicted its action for ``observation`` (the robot's raw observation),
        before that action is sent. STAC assumes one policy call per control step (synchronous inference)."""
        stale = False
        if self._watchdog is not None and CAMERA in observation:
            pose = np.array([float(observation[k]) for k in POSE_FEATURES])
            stale = self._watchdog.update(np.asarray(observation[CAMERA]), pose)
        threshold, flagged, new = math.nan, False, False
        if self.kind == "ensemble":
            status = self.policy.ood_status()
            new = bool(status["new_prediction"])
            self._score, threshold, flagged = (
                float(status["score"]),
                float(status["threshold"]),
                status["decision"],
            )
        elif self.kind == "stac":
            threshold = self._calibration.threshold
            if self._capture.chunks > self._chunks:
                self._chunks, new = self._capture.chunks, True
                self._score = self._monitor.update(self._capture.last)
            flagged = self._monitor.episode_max > threshold
        self._latched = self._latched or bool(flagged) or stale
        return GateReading(self._score, threshold, self._latched, stale, new)
