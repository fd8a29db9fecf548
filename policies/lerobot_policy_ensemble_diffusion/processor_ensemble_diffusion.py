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
from typing import Any

import torch
from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors

from .configuration_ensemble_diffusion import EnsembleDiffusionConfig


def make_ensemble_diffusion_pre_post_processors(
    config: EnsembleDiffusionConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    """Pre- and post-processor pipelines of the ensemble: the same as a single diffusion policy's.

    All members share one normalization (one dataset), so the ensemble's processors are LeRobot's default
    diffusion ones: rename -> add batch dim -> device -> normalize, and unnormalize -> cpu. This is also what
    makes separately trained `diffusion` members assemblable (their processor files are reused as they are).

    Args:
        config: The ensemble policy configuration (features, normalization mapping, device).
        dataset_stats: Statistics used for normalization. Defaults to None.

    Returns:
        The (pre-processor, post-processor) pipelines.
    """
    return make_default_pre_post_processors(config, dataset_stats)
