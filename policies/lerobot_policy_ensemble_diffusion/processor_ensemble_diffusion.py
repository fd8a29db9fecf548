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
from lerobot.processor import PolicyAction, PolicyProcessorPipeline
from lerobot.processor.factory import make_default_policy_processor_steps, make_policy_processor_pipelines

from .configuration_ensemble_diffusion import EnsembleDiffusionConfig
from .jaw_frame_actions import JawFrameAbsoluteActionsStep, state_cache_step


def make_ensemble_diffusion_pre_post_processors(
    config: EnsembleDiffusionConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    """Pre- and post-processor pipelines of the ensemble: a single diffusion policy's, and for a policy trained
    on relative actions the pair that composes them with the measured jaw pose.

    All members share one normalization (one dataset), so the ensemble's processors are LeRobot's default
    diffusion ones: rename -> add batch dim -> device -> normalize, and unnormalize -> cpu. This is also what
    makes separately trained `diffusion` members assemblable (their processor files are reused as they are).
    With `config.relative_actions` the pre-processor caches the raw state after batching, and the
    post-processor turns each unnormalized action into its absolute target (`jaw_frame_actions.py`).

    Args:
        config: The ensemble policy configuration (features, normalization mapping, device).
        dataset_stats: Statistics used for normalization. Defaults to None.

    Returns:
        The (pre-processor, post-processor) pipelines.
    """
    s = make_default_policy_processor_steps(config, dataset_stats)
    input_steps = [s.rename_observations, s.add_batch_dim, s.to_device, s.normalize]
    output_steps = [s.unnormalize, s.to_cpu]
    if config.relative_actions:
        cache = state_cache_step()
        input_steps.insert(2, cache)
        output_steps.append(JawFrameAbsoluteActionsStep(relative_step=cache))
    return make_policy_processor_pipelines(input_steps=input_steps, output_steps=output_steps)
