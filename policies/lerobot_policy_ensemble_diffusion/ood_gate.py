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
import math
from pathlib import Path

from torch import Tensor

from lerobot_suture.safety.ood.calibration import OODCalibration
from lerobot_suture.safety.ood.gate import OODGate

from .configuration_ensemble_diffusion import EnsembleDiffusionConfig

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
                f"for this policy's scores. Recalibrate with `lerobot-suture calibrate "
                f"--policy.path={directory}` or set the policy's options back."
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
        return {
            "score": math.nan,
            "threshold": math.nan,
            "decision": False,
            "released": False,
            "new_prediction": False,
        }
    gate = gates[index]
    return {
        "score": float(gate.last_score),
        "threshold": float(gate.threshold),
        "decision": bool(gate.decision),
        "released": bool(gate.released and enforce),
        "new_prediction": new_prediction,
    }
