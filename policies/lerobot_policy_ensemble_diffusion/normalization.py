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
"""LeRobot's normalization of a feature, undone: the affine map back to dataset units, from dataset
statistics or from the preprocessor saved beside a policy."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from lerobot.configs import NormalizationMode
from lerobot.utils.constants import ACTION
from torch import Tensor


def action_affine_from_stats(
    stats: dict[str, dict], mode: NormalizationMode, eps: float = 1e-8, key: str = ACTION
) -> tuple[Tensor, Tensor]:
    """The map x_norm -> x = x_norm * scale + offset that inverts LeRobot's normalization of ``key``.

    Mirrors `lerobot.processor.normalize_processor` (`_apply_transform(..., inverse=True)`), which is affine in
    every mode.

    Args:
        stats: dataset statistics, {"action": {"mean"|"std"|"min"|"max"|"q01"|...: (A,)}}.
        mode: the normalization mode of ``key``.
        key: the feature (default the action; the OOD gate's hold action also needs the state's).
    Returns:
        scale: (A,), offset: (A,) float32.
    """
    if key not in stats:
        raise ValueError(f"`dataset_stats` has no '{key}' entry. Got keys {sorted(stats)}.")
    action_stats = {
        k: torch.as_tensor(np.asarray(v.cpu() if isinstance(v, Tensor) else v), dtype=torch.float32)
        for k, v in stats[key].items()
    }

    def need(*names: str) -> list[Tensor]:
        missing = [n for n in names if n not in action_stats]
        if missing:
            raise ValueError(
                f"{mode.value} normalization of '{key}' needs stats {missing}; got {sorted(action_stats)}."
            )
        return [action_stats[n] for n in names]

    if mode == NormalizationMode.IDENTITY:
        dim = next(iter(action_stats.values())).shape[-1]
        return torch.ones(dim), torch.zeros(dim)
    if mode == NormalizationMode.MEAN_STD:
        mean, std = need("mean", "std")
        return std.clone(), mean.clone()
    low_high = {
        NormalizationMode.MIN_MAX: ("min", "max"),
        NormalizationMode.QUANTILES: ("q01", "q99"),
        NormalizationMode.QUANTILE10: ("q10", "q90"),
    }
    if mode not in low_high:
        raise ValueError(f"Unsupported normalization mode for '{key}': {mode}.")
    low, high = need(*low_high[mode])
    denom = high - low
    denom = torch.where(denom == 0, torch.tensor(eps), denom)
    return denom / 2, low + denom / 2


def saved_normalizer_stats(directory: Path) -> dict | None:
    """The statistics of the normalizer step in the preprocessor saved beside the policy, if any."""
    from lerobot.processor import PolicyProcessorPipeline

    if not (directory / "policy_preprocessor.json").is_file():
        return None
    pipeline = PolicyProcessorPipeline.from_pretrained(directory, config_filename="policy_preprocessor.json")
    for step in pipeline.steps:
        stats = getattr(step, "stats", None)
        if stats:
            return stats
    return None
