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
"""Whether what a policy is given fits it: a dataset's features, an observation, a checkpoint's tensors.
Each check raises a ValueError that names every mismatch."""

from __future__ import annotations

import re

from lerobot.utils.constants import OBS_IMAGES, OBS_STATE
from safetensors import safe_open
from torch import Tensor, nn

from .configuration_ensemble_diffusion import EnsembleDiffusionConfig

MEMBERS_PREFIX = "members"
_MEMBER_KEY = re.compile(rf"^{MEMBERS_PREFIX}\.(\d+)\.")


def check_features_match(config: EnsembleDiffusionConfig, features: dict, source: str) -> None:
    """Raise a ValueError naming every policy input/output feature that `features` lacks or shapes differently.

    Args:
        config: the policy config (its `input_features` / `output_features`).
        features: LeRobot dataset features ({"key": {"dtype", "shape", ...}}) or policy features.
        source: what `features` describe, for the message (e.g. "dataset local/suture").
    """
    from lerobot.utils.feature_utils import dataset_to_policy_features

    if features and isinstance(next(iter(features.values())), dict):
        features = dataset_to_policy_features(features)
    problems = []
    for kind, expected in (("input", config.input_features or {}), ("output", config.output_features or {})):
        for key, ft in expected.items():
            if key not in features:
                problems.append(f"{kind} feature '{key}' {tuple(ft.shape)} is missing")
            elif tuple(features[key].shape) != tuple(ft.shape):
                problems.append(
                    f"{kind} feature '{key}' has shape {tuple(features[key].shape)} there but {tuple(ft.shape)} "
                    "in the policy"
                )
    if problems:
        raise ValueError(f"The policy's features do not match the {source}: " + "; ".join(problems) + ".")


def check_observation(config: EnsembleDiffusionConfig, batch: dict[str, Tensor]) -> None:
    """Raise a clear error when a stacked observation, (B, n_obs_steps, ...) per key, does not match the
    features the policy was built for."""
    state_dim = config.robot_state_feature.shape[0]
    if batch[OBS_STATE].shape[-1] != state_dim:
        raise ValueError(
            f"'{OBS_STATE}' has {batch[OBS_STATE].shape[-1]} dimensions but the policy was trained with "
            f"{state_dim} (config.input_features). Check the env/dataset features."
        )
    if config.n_obs_steps != batch[OBS_STATE].shape[1]:
        raise ValueError(f"Expected {config.n_obs_steps} observation steps, got {batch[OBS_STATE].shape[1]}.")
    if config.image_features:
        images = batch[OBS_IMAGES]  # (B, S, n_cameras, C, H, W)
        expected = next(iter(config.image_features.values())).shape
        got = tuple(images.shape[-3:])
        same_size = config.resize_shape is not None or got[1:] == tuple(expected[1:])
        if got[0] != expected[0] or not same_size:
            raise ValueError(
                f"Images have shape {got} but the policy was trained with {tuple(expected)} "
                f"({list(config.image_features)}). Check the env/dataset camera features."
            )


def check_checkpoint_matches(model: nn.Module, model_file: str) -> None:
    """Raise a clear error when `model_file` does not hold exactly the tensors `model` (the ensemble policy)
    expects.

    Names missing or extra members (against `config.n_members`), missing or unexpected keys, and tensors whose
    shapes differ (typically: features or architecture settings that differ from the checkpoint's).
    """
    expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    with safe_open(model_file, framework="pt") as f:
        found = {k: tuple(f.get_slice(k).get_shape()) for k in f.keys()}  # noqa: SIM118

    def members_of(keys) -> set[int]:
        return {int(m.group(1)) for k in keys if (m := _MEMBER_KEY.match(k))}

    found_members, expected_members = members_of(found), members_of(expected)
    problems = []
    if found_members != expected_members:
        missing = sorted(expected_members - found_members)
        extra = sorted(found_members - expected_members)
        problems.append(
            f"the checkpoint holds members {sorted(found_members)} but the config has n_members="
            f"{model.config.n_members}"
            + (f" (missing member(s) {missing})" if missing else "")
            + (f" (unexpected member(s) {extra})" if extra else "")
        )
    common_members = found_members & expected_members

    def relevant(key: str) -> bool:
        m = _MEMBER_KEY.match(key)
        return m is None or int(m.group(1)) in common_members

    missing_keys = sorted(k for k in expected if k not in found and relevant(k))
    unexpected_keys = sorted(k for k in found if k not in expected and relevant(k))
    if missing_keys:
        problems.append(f"{len(missing_keys)} missing tensor(s), e.g. {missing_keys[:5]}")
    if unexpected_keys:
        problems.append(f"{len(unexpected_keys)} unexpected tensor(s), e.g. {unexpected_keys[:5]}")
    mismatched = [
        f"{k}: checkpoint {found[k]} vs policy {expected[k]}"
        for k in sorted(expected)
        if k in found and found[k] != expected[k]
    ]
    if mismatched:
        problems.append(
            f"{len(mismatched)} tensor(s) with mismatched shapes (do the input/output features or architecture "
            f"settings differ from the checkpoint's?), e.g. {mismatched[:5]}"
        )
    if problems:
        raise ValueError(f"{model_file} does not match the ensemble policy: " + "; ".join(problems) + ".")
