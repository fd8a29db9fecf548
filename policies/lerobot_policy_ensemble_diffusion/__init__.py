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
"""LeRobot policy plugin `ensemble_diffusion`: N diffusion policies, mean action and covariance.

Importing the package registers `EnsembleDiffusionConfig` as policy type "ensemble_diffusion" (LeRobot
imports installed `lerobot_policy_*` distributions on start). The policy, the processor factory and the
assembly helpers are imported on first use, so registration stays light.
"""

from importlib import import_module

from .configuration_ensemble_diffusion import EnsembleDiffusionConfig, EnsembleOODConfig
from .jaw_frame_actions import JawFrameAbsoluteActionsStep  # registered: a saved post-processor names it

_LAZY = {
    "EnsembleDiffusionPolicy": "modeling_ensemble_diffusion",
    "EnsemblePrediction": "prediction",
    "make_ensemble_diffusion_pre_post_processors": "processor_ensemble_diffusion",
    "assemble_members": "assemble",
    "export_member": "assemble",
    "EnsembleActionStats": "ensemble_stats",
    "compute_ensemble_stats": "ensemble_stats",
    "ensemble_mean": "ensemble_stats",
    "ensemble_covariance": "ensemble_stats",
    "total_covariance_split": "ensemble_stats",
}

__all__ = ["EnsembleDiffusionConfig", "EnsembleOODConfig", "JawFrameAbsoluteActionsStep", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
