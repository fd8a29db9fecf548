#!/usr/bin/env python

# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.
"""The O.O.D. gate in the policy: which calibration a policy may use, one gate per env of the batch fed
with each new prediction's score, and the gate's status for logging. The gate itself (score model,
likelihood-ratio test, latch) is `lerobot_suture.safety.ood`."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import torch
from lerobot.configs import FeatureType, NormalizationMode
from lerobot.utils.constants import OBS_STATE
from torch import Tensor

from lerobot_suture.safety.ood.calibration import OODCalibration
from lerobot_suture.safety.ood.calibration_file import load_calibration
from lerobot_suture.safety.ood.gate import OODGate, silent_status
from lerobot_suture.sim.relative_actions import STILL_MOTION

from .configuration_ensemble_diffusion import EnsembleDiffusionConfig
from .normalization import action_affine_from_stats

logger = logging.getLogger(__name__)


def check_calibration_fits(
    calibration: OODCalibration, config: EnsembleDiffusionConfig, directory: str | Path
) -> None:
    """Raise a ValueError when `calibration` was fitted on another score, or with other score settings,
    than the policy of `config` computes (its threshold would not hold for them)."""
    if (calibration.score_name, calibration.space) != (
        config.uncertainty_score,
        config.uncertainty_space,
    ):
        raise ValueError(
            f"The calibration in {directory} was fitted on score {calibration.score_name!r} in "
            f"{calibration.space} space, but this policy computes {config.uncertainty_score!r} in "
            f"{config.uncertainty_space} space. Recalibrate with `lerobot-suture calibrate "
            f"--policy.path={directory}` or set the policy's uncertainty options to match."
        )
    if calibration.score_settings is not None:  # None: a file from before they were recorded
        ours = config.score_settings()
        differ = {
            key: (value, ours.get(key))
            for key, value in calibration.score_settings.items()
            if ours.get(key) != value
        }
        if differ:
            described = ", ".join(
                f"{key}={fitted!r} (this policy: {current!r})" for key, (fitted, current) in differ.items()
            )
            raise ValueError(
                f"The calibration in {directory} was fitted with {described}; its threshold does not hold "
                f"for this policy's scores. Set the policy's options back, or calibrate a copy with them: "
                f"`lerobot-suture calibrate --policy.path={directory} --policy.OPTION=VALUE ... "
                f"--copy_to=COPY` writes them into the copy's config.json (a policy saved with them: "
                f"`lerobot-suture calibrate --policy.path={directory}`)."
            )


def update_gates(
    gates: list[OODGate], scores: Tensor, calibration: OODCalibration | None, config: EnsembleDiffusionConfig
) -> list[OODGate]:
    """Feed each env's gate its new prediction's score, (B,); returns the gates (new ones when the batch
    size changed, as at the first prediction of an episode)."""
    if config.ood.enforce and calibration is None:
        raise ValueError(
            "`ood.enforce=true` needs a calibration of the O.O.D. gate, and this policy has none. Run "
            "`lerobot-suture calibrate --policy.path=DIR` on the trained policy directory (it writes "
            f"{config.ood.calibration_file} there), or set `--policy.ood.enforce=false` to report only."
        )
    values = scores.detach().cpu().tolist()
    if len(gates) != len(values):
        gates = [OODGate(calibration=calibration, enforce=config.ood.enforce) for _ in values]
    for index, (gate, value) in enumerate(zip(gates, values, strict=True)):
        was_released = gate.released
        gate.update(value)
        if gate.released and not was_released:
            # The one report a user of `lerobot-eval` sees: the rollout loop there knows nothing of gates.
            logger.info(
                "O.O.D. gate: env %d flagged at prediction %d (score %.4g > threshold %.4g); %s",
                index,
                gate.released_at,
                gate.last_score,
                gate.threshold,
                "control released to the surgeon, the arm holds its pose"
                if config.ood.enforce
                else "reported only (ood.enforce=false)",
            )
    return gates


def gate_status(gates: list[OODGate], index: int, enforce: bool, new_prediction: bool) -> dict:
    """The gate's state for batch element `index`, for logging (see `EnsembleDiffusionPolicy.ood_status`)."""
    if index >= len(gates):
        return silent_status()
    gate = gates[index]
    return {
        "score": float(gate.last_score),
        "threshold": float(gate.threshold),
        "decision": bool(gate.decision),
        "released": bool(gate.released and enforce),
        "flagged": bool(gate.released),
        "new_prediction": new_prediction,
    }


class GatedPolicyMixin:
    """The gate's side of :class:`~.modeling_ensemble_diffusion.EnsembleDiffusionPolicy`: its calibration,
    the per-env gates, the hold action and the status a rollout logs. Reads the policy's `config`, its
    normalization buffers, `_ood_gates` and `_new_prediction`."""

    def set_state_normalization(self, stats: dict[str, dict]) -> None:
        """Learn the state's normalization (for the gate's hold action) from dataset-style statistics."""
        mode = NormalizationMode(
            (self.config.normalization_mapping or {}).get(FeatureType.STATE.value, NormalizationMode.IDENTITY)
        )
        scale, offset = action_affine_from_stats(stats, mode, key=OBS_STATE)
        with torch.no_grad():
            self.state_unnormalize_scale.copy_(scale)
            self.state_unnormalize_offset.copy_(offset)

    def load_ood_calibration(self, directory: str | Path) -> OODCalibration:
        """Load the gate's calibration from `directory / config.ood.calibration_file`.

        Raises:
            CalibrationNotFoundError: the file is missing (its message says how to calibrate).
            ValueError: the file is malformed, or was fitted on another score than this policy computes.
        """
        calibration = load_calibration(directory, filename=self.config.ood.calibration_file)
        check_calibration_fits(calibration, self.config, directory)
        self.ood_calibration = calibration
        self._ood_gates = []
        return calibration

    def _update_ood_gates(self, scores: Tensor) -> None:
        released = any(gate.released for gate in self._ood_gates)
        self._ood_gates = update_gates(self._ood_gates, scores, self.ood_calibration, self.config)
        if not released and any(gate.released for gate in self._ood_gates):
            # When (time.perf_counter, s) the gate first flagged: a rollout measures its handover from it.
            self.ood_flagged_at = time.perf_counter()

    def _hold_action(self, batch: dict[str, Tensor]) -> Tensor:
        """The measured pose as a normalized action, (B, A): the arm stops where it is. For a policy of
        relative actions, the motion that keeps the measured pose (its post-processor composes it)."""
        if not bool(torch.isfinite(self.state_unnormalize_scale).all()) or not self.has_action_stats:
            raise ValueError(
                "The O.O.D. gate released control but the policy cannot form a hold action: it does not know "
                "the state and action normalization. Load the policy with `from_pretrained` from a lerobot-train "
                "checkpoint directory (it reads them from the saved preprocessor)."
            )
        state = batch[OBS_STATE]  # (B, S), normalized, the current observation
        pose = state * self.state_unnormalize_scale + self.state_unnormalize_offset
        if self.config.relative_actions:
            still = torch.as_tensor(STILL_MOTION, dtype=pose.dtype, device=pose.device)
            pose = torch.cat([still.expand(pose.shape[0], -1), pose[:, -1:]], dim=1)
        return (pose - self.action_unnormalize_offset) / self.action_unnormalize_scale

    def _hold_where_released(self, actions: Tensor, batch: dict[str, Tensor]) -> Tensor:
        """`actions` (B, S, A), with the hold action for each batch element whose enforced gate released."""
        if not self.config.ood.enforce or not self._ood_gates:
            return actions
        released = torch.tensor([gate.released for gate in self._ood_gates], device=actions.device)
        if not released.any():
            return actions
        hold = self._hold_action(batch)[:, None].expand_as(actions)
        return torch.where(released[:, None, None], hold, actions)

    def ood_status(self, index: int = 0) -> dict:
        """The gate's state for batch element `index` after the last `select_action`, for logging.

        Keys: `score` (the last prediction's uncertainty score), `threshold` (NaN without a calibration),
        `decision` (the last test said O.O.D.), `released` (control was released, latched until `reset`),
        `flagged` (the gate has said O.O.D. this episode, latched, enforced or not), `new_prediction` (this call
        predicted a new chunk).
        """
        return gate_status(self._ood_gates, index, self.config.ood.enforce, self._new_prediction)
