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
"""Ensemble of N LeRobot diffusion policies ("Safe Uncertainty-Aware Learning of Robotic Suturing").

The members are plain LeRobot `DiffusionPolicy` modules (`self.members[n]`), trained together on one data
pipeline (loss = mean of the member losses) from independent initialisations. At inference every member
samples an action chunk for the same observation; the ensemble executes the mean chunk and reports the
per-step covariance, whose largest absolute entry is the paper's uncertainty score sigma_hat.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from lerobot.configs import FeatureType, NormalizationMode
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.policies.utils import populate_queues
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_IMAGES, OBS_STATE
from lerobot.utils.device_utils import resolve_safetensors_device
from lerobot.utils.import_utils import require_package
from safetensors.torch import load_model as load_model_as_safetensor
from torch import Tensor, nn

from lerobot_suture.lerobot_shim import prepare_global_conditioning
from lerobot_suture.safety.ood.calibration import OODCalibration
from lerobot_suture.safety.ood.gate import OODGate

from .batched_members import FusedDiffusionEnsemble
from .compatibility import check_checkpoint_matches, check_features_match, check_observation
from .configuration_ensemble_diffusion import NEEDLE_KEYPOINTS_KEY, SCORE_CHOICES, EnsembleDiffusionConfig
from .ensemble_stats import compute_ensemble_stats
from .feature_capture import FeatureCapture, FeatureCaptureMixin
from .members import bootstrap_batch, captured_outputs, image_encoders, make_member
from .needle_keypoints import make_needle_heads, needle_keypoint_error
from .normalization import action_affine_from_stats, saved_normalizer_stats
from .ood_gate import GatedPolicyMixin
from .prediction import EnsemblePrediction, score_ensemble_stats
from .rtc_inpainting import committed_prefix, conditional_sample

if TYPE_CHECKING:
    from lerobot.datasets import LeRobotDatasetMetadata


class EnsembleDiffusionPolicy(GatedPolicyMixin, FeatureCaptureMixin, PreTrainedPolicy):
    """N LeRobot `DiffusionPolicy` members trained and run as one policy; mean action plus covariance."""

    config_class = EnsembleDiffusionConfig
    name = "ensemble_diffusion"

    def __init__(
        self,
        config: EnsembleDiffusionConfig,
        dataset_stats: dict[str, dict] | None = None,
        dataset_meta: LeRobotDatasetMetadata | None = None,
        **kwargs,
    ):
        """
        Args:
            config: Policy configuration.
            dataset_stats: Dataset statistics; the action statistics give the unnormalized covariance. When
                loading a checkpoint they replace the saved ones (as they replace the processor's).
            dataset_meta: Dataset metadata; its features are checked against `config.input_features`.
        """
        require_package("diffusers", extra="diffusion")
        super().__init__(config)
        config.validate_features()
        if config.action_feature is None or config.robot_state_feature is None:
            raise ValueError(
                f"`input_features` must hold '{OBS_STATE}' and `output_features` must hold '{ACTION}'. "
                f"Got input_features={sorted(config.input_features or {})}, "
                f"output_features={sorted(config.output_features or {})}."
            )
        if dataset_meta is not None:
            check_features_match(config, dataset_meta.features, source=f"dataset {dataset_meta.repo_id}")
        self.config = config

        members = []
        for i in range(config.n_members):
            if config.member_seeds is None:
                members.append(make_member(config))
            else:
                with torch.random.fork_rng(devices=[]):
                    torch.manual_seed(config.member_seeds[i])
                    members.append(make_member(config))
        self.members = nn.ModuleList(members)
        # Training-only heads of the auxiliary needle loss, one per member, on its image features.
        self.needle_heads: nn.ModuleList | None = make_needle_heads(config, members)

        action_dim = config.action_feature.shape[0]
        # x = x_norm * scale + offset inverts the action normalization (NaN: unknown until stats are given).
        self.register_buffer("action_unnormalize_scale", torch.full((action_dim,), math.nan))
        self.register_buffer("action_unnormalize_offset", torch.full((action_dim,), math.nan))
        self._given_action_affine = None
        if dataset_stats is not None and ACTION in dataset_stats:
            self._given_action_affine = action_affine_from_stats(dataset_stats, self._action_norm_mode())
            self._apply_given_action_affine()
        # The O.O.D. gate's hold action is the measured pose: the state's normalization is needed to turn it
        # into a normalized action. Not saved with the weights; set from the dataset statistics or, on
        # loading, from the saved preprocessor (see `from_pretrained`).
        state_dim = config.robot_state_feature.shape[0]
        self.register_buffer("state_unnormalize_scale", torch.full((state_dim,), math.nan), persistent=False)
        self.register_buffer("state_unnormalize_offset", torch.full((state_dim,), math.nan), persistent=False)
        if dataset_stats is not None and OBS_STATE in dataset_stats:
            self.set_state_normalization(dataset_stats)
        # The gate's calibration (`lerobot-suture calibrate`); loaded by `from_pretrained`.
        self.ood_calibration: OODCalibration | None = None

        # Fused inference copy of the members, in a plain dict so that it is no submodule (not saved, not
        # moved by `.to()`); rebuilt when the members' tensors change.
        self._fused_cache: dict = {}
        self.last_prediction: EnsemblePrediction | None = None
        # What failure detectors read besides the prediction (`enable_feature_capture`); off by default.
        self._capture: FeatureCapture | None = None
        self.reset()

    # ---- bookkeeping --------------------------------------------------------------------------------

    def _action_norm_mode(self) -> NormalizationMode:
        mapping = self.config.normalization_mapping or {}
        mode = mapping.get(
            FeatureType.ACTION.value, mapping.get(FeatureType.ACTION, NormalizationMode.IDENTITY)
        )
        return NormalizationMode(mode)

    def _apply_given_action_affine(self) -> None:
        if self._given_action_affine is not None:
            scale, offset = self._given_action_affine
            with torch.no_grad():
                self.action_unnormalize_scale.copy_(scale)
                self.action_unnormalize_offset.copy_(offset)

    @property
    def has_action_stats(self) -> bool:
        """Whether the policy knows how to unnormalize actions (for unnormalized statistics)."""
        return bool(torch.isfinite(self.action_unnormalize_scale).all())

    def get_optim_params(self) -> dict:
        return self.parameters()

    def reset(self):
        """Clear observation and action queues and the last prediction. Call on `env.reset()`."""
        self._queues = {
            OBS_STATE: deque(maxlen=self.config.n_obs_steps),
            ACTION: deque(maxlen=self.config.n_action_steps),
        }
        if self.config.image_features:
            self._queues[OBS_IMAGES] = deque(maxlen=self.config.n_obs_steps)
        if self.config.env_state_feature:
            self._queues[OBS_ENV_STATE] = deque(maxlen=self.config.n_obs_steps)
        self.last_prediction = None
        self._ood_gates: list[OODGate] = []  # one per batch element, made at the first prediction
        self._new_prediction = False

    def train(self, mode: bool = True):
        self.invalidate_fused_cache()
        return super().train(mode)

    def invalidate_fused_cache(self) -> None:
        """Drop the fused inference copy of the members (rebuilt on the next prediction).

        Needed only after writing into parameters through `.data` (which torch does not version); optimizer
        steps, `load_state_dict`, device or dtype moves and `train()`/`eval()` are detected automatically.
        """
        if hasattr(self, "_fused_cache"):
            self._fused_cache.clear()

    def _fused_members(self) -> FusedDiffusionEnsemble:
        tensors = [*self.members.parameters(), *self.members.buffers()]
        key = (tensors[0].device, tensors[0].dtype, tuple(t._version for t in tensors))
        if self._fused_cache.get("key") != key:
            self._fused_cache.clear()
            with torch.no_grad():
                self._fused_cache["model"] = FusedDiffusionEnsemble([m.diffusion for m in self.members])
            self._fused_cache["key"] = key
        return self._fused_cache["model"]

    # ---- training -----------------------------------------------------------------------------------
    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """Mean of the member losses on one shared batch (each member's own bootstrap resample if enabled).

        Returns:
            loss: scalar tensor, the mean of the N member losses.
            output: {"loss_member_<n>": float} per member, for logging, and with `needle_keypoints_weight` > 0
                "loss_needle_keypoints": the auxiliary loss's mean squared error, averaged over the members.

        With `needle_keypoints_weight` > 0 the loss adds that weight times the auxiliary error.
        """
        batch_size = batch[OBS_STATE].shape[0]
        if self.needle_heads is not None and NEEDLE_KEYPOINTS_KEY not in batch:
            raise ValueError(
                f"`needle_keypoints_weight` > 0 needs '{NEEDLE_KEYPOINTS_KEY}' in the batch; got keys "
                f"{sorted(batch)}. Train on a dataset recorded by `lerobot-suture record`."
            )
        losses, needle_errors = [], []
        for n, member in enumerate(self.members):
            member_batch = batch
            if self.config.bootstrap and self.training:
                index = torch.randint(0, batch_size, (batch_size,), device=batch[OBS_STATE].device)
                member_batch = bootstrap_batch(batch, index, batch_size)
            if self.needle_heads is None:
                loss, _ = member.forward(member_batch)
            else:
                with captured_outputs(image_encoders(member)) as encoded:
                    loss, _ = member.forward(member_batch)
                needle_errors.append(
                    needle_keypoint_error(
                        self.needle_heads[n],
                        member,
                        n,
                        encoded,
                        member_batch[NEEDLE_KEYPOINTS_KEY],
                        self.config.n_obs_steps,
                        batch_size,
                    )
                )
            losses.append(loss)
        losses = torch.stack(losses)  # (N,)
        output = {f"loss_member_{n}": value for n, value in enumerate(losses.detach().cpu().tolist())}
        total = losses.mean()
        if needle_errors:
            needle_error = torch.stack(needle_errors).mean()
            output["loss_needle_keypoints"] = needle_error.item()
            total = total + self.config.needle_keypoints_weight * needle_error
        return total, output

    # ---- inference ----------------------------------------------------------------------------------

    def _stack_observation(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """The (B, n_obs_steps, ...) model input, from the queues (online) or from `batch` (offline)."""
        if any(len(q) > 0 for q in self._queues.values()):
            return {k: torch.stack(list(self._queues[k]), dim=1) for k in batch if k in self._queues}
        batch = dict(batch)
        if self.config.image_features:
            for key in self.config.image_features:
                if batch[key].ndim == 4:
                    batch[key] = batch[key].unsqueeze(1)
            batch[OBS_IMAGES] = torch.stack([batch[key] for key in self.config.image_features], dim=-4)
        return batch

    def _sample(
        self,
        batch: dict[str, Tensor],
        samples_per_member: int,
        noise: Tensor | None,
        generator: torch.Generator | None,
        prefix: Tensor | None = None,
    ) -> Tensor:
        """Every member's K sampled chunks over the full horizon: (B, N, K, T, A); with a committed `prefix`
        (L, A), every chunk starts with it at step n_obs_steps - 1 (`rtc_inpainting`)."""
        batch_size = batch[OBS_STATE].shape[0]
        k = samples_per_member
        n = self.config.n_members
        t_len, a = self.config.horizon, self.config.action_feature.shape[0]
        if noise is not None and tuple(noise.shape) != (batch_size, n, k, t_len, a):
            raise ValueError(
                f"`noise` must have shape (B, N, K, T, A) = {(batch_size, n, k, t_len, a)}. Got {tuple(noise.shape)}."
            )
        if self.config.batched_inference and n > 1 and not self.training:  # one member: nothing to fuse
            fused = self._fused_members()
            global_cond = fused.encode(batch)  # (B, N, G)
            out = fused.sample(
                global_cond,
                samples_per_member=k,
                noise=noise,
                generator=generator,
                prefix=prefix,
                first_step=self.config.n_obs_steps - 1,
            )
            self._capture_features(global_cond)
            return out
        samples, conds = [], []
        for i, member in enumerate(self.members):
            model = member.diffusion
            global_cond = prepare_global_conditioning(model, batch)  # (B, G)
            conds.append(global_cond)
            global_cond = global_cond.repeat_interleave(k, dim=0)  # (B*K, G)
            member_noise = None if noise is None else noise[:, i].reshape(batch_size * k, t_len, a)
            chunk = conditional_sample(
                model,
                batch_size * k,
                global_cond,
                generator,
                member_noise,
                prefix,
                self.config.n_obs_steps - 1,
            )  # (B*K, T, A)
            samples.append(chunk.view(batch_size, k, t_len, a))
        self._capture_features(torch.stack(conds, dim=1))  # (B, N, G)
        return torch.stack(samples, dim=1)  # (B, N, K, T, A)

    @torch.no_grad()
    def predict_action_distribution(
        self,
        batch: dict[str, Tensor],
        samples_per_member: int | None = None,
        noise: Tensor | None = None,
        generator: torch.Generator | None = None,
        prefix: Tensor | None = None,
    ) -> EnsemblePrediction:
        """Sample every member on the same observation and return the ensemble statistics.

        Uses the observation queues when `select_action` has filled them, otherwise `batch` directly (a
        dataloader batch with n_obs_steps observations, or a single observation with n_obs_steps = 1).
        The result is also kept in `self.last_prediction`.

        Args:
            batch: normalized observation (the preprocessor's output).
            samples_per_member: K chunks per member (default `config.uncertainty_samples_per_member`); K > 1
                gives the aleatoric / epistemic split.
            noise: optional initial noise (B, N, K, horizon, A).
            generator: optional RNG for the diffusion noise.
            prefix: optional (L, A) normalized actions committed already (real-time chunking): every sampled
                chunk starts with them, and the score is read over the executed steps after them.
        Returns:
            EnsemblePrediction over the full horizon: samples (B, N, K, T, A), member_mean (B, N, T, A),
            mean (B, T, A), covariance / epistemic / aleatoric (B, T, A, A), normalized and unnormalized, and
            the score (B,).
        """
        k = self.config.uncertainty_samples_per_member if samples_per_member is None else samples_per_member
        if k < 1:
            raise ValueError(f"`samples_per_member` must be >= 1. Got {k}.")
        if self.config.uncertainty_source == "aleatoric" and k < 2:
            raise ValueError("`uncertainty_source`='aleatoric' needs `samples_per_member` >= 2.")
        model_batch = self._stack_observation(batch)
        check_observation(self.config, model_batch)
        # Always full precision, also under lerobot-eval's `use_amp` autocast: bf16 sampling moves the
        # score, and the gate's calibration is only valid for the numerics it was fitted with.
        with torch.autocast(model_batch[OBS_STATE].device.type, enabled=False):
            return self._predict(model_batch, k, noise, generator, prefix)

    def _predict(
        self,
        model_batch: dict[str, Tensor],
        k: int,
        noise: Tensor | None,
        generator: torch.Generator | None,
        prefix: Tensor | None = None,
    ) -> EnsemblePrediction:
        samples = self._sample(model_batch, k, noise, generator, prefix)  # (B, N, K, T, A)
        normalized = compute_ensemble_stats(samples, correction=self.config.covariance_correction)
        unnormalized = None
        if self.has_action_stats:
            unnormalized = normalized.affine(self.action_unnormalize_scale, self.action_unnormalize_offset)
        # The executed steps; with a committed prefix, the ones after it (where the members are free to differ).
        committed = 0 if prefix is None else prefix.shape[0]
        start = self.config.n_obs_steps - 1
        start += min(committed, self.config.horizon - start - self.config.n_action_steps)
        action_steps = slice(start, start + self.config.n_action_steps)
        score = score_ensemble_stats(
            normalized, unnormalized, action_steps, self._score_choice(), logdet_eps=self.config.logdet_eps
        )  # (B,)
        prediction = EnsemblePrediction(
            normalized=normalized,
            unnormalized=unnormalized,
            score=score,
            score_name=self.config.uncertainty_score,
            score_space=self.config.uncertainty_space,
            score_source=self.config.uncertainty_source,
            action_steps=action_steps,
        )
        self.last_prediction = prediction
        return prediction

    @property
    def uncertainty(self) -> Tensor | None:
        """(B,) the last prediction's uncertainty score (sigma_hat by default); None before the first."""
        return None if self.last_prediction is None else self.last_prediction.score

    def _score_choice(self) -> dict[str, str]:
        return {name: getattr(self.config, name) for name in SCORE_CHOICES}

    def rescore(self, prediction: EnsemblePrediction, **choice: str) -> Tensor:
        """(B,) the score of `prediction` (e.g. `self.last_prediction`) under another `choice` of the config's
        `uncertainty_*` fields (those left out keep this policy's): the same samples scored another way, as
        `lerobot-suture score-study` compares them on validation episodes."""
        unknown = sorted(set(choice) - set(SCORE_CHOICES))
        if unknown:
            raise ValueError(f"Unknown score settings {unknown}: choose among {list(SCORE_CHOICES)}.")
        return score_ensemble_stats(
            prediction.normalized,
            prediction.unnormalized,
            prediction.action_steps,
            {**self._score_choice(), **choice},
            logdet_eps=self.config.logdet_eps,
        )

    def supports_rtc(self) -> bool:
        """LeRobot's real-time chunking engine may run this policy (`lerobot-rollout --inference.type=rtc`)."""
        return True

    @torch.no_grad()
    def predict_action_chunk(
        self,
        batch: dict[str, Tensor],
        noise: Tensor | None = None,
        inference_delay: int | None = None,
        prev_chunk_left_over: Tensor | None = None,
    ) -> Tensor:
        """The ensemble mean in normalized action space, `noise` optional initial noise (B, N, K, horizon, A).

        Without `inference_delay`: the executed steps, (B, n_action_steps, A), online (queues filled by
        `select_action`) or offline (dataloader batch), as `DiffusionPolicy`. With it, LeRobot's real-time
        chunking engine calls (`rtc_inpainting`): `batch` is the latest observation, `prev_chunk_left_over` what
        is left of the current chunk. The chunk runs from the observation's step to the horizon's end, its first
        `inference_delay` steps the committed actions. The gate reads the score first (`rtc_score`); once it
        released control with `ood.enforce`, the chunk holds the measured pose: no flagged chunk executes."""
        if inference_delay is None:
            prediction = self.predict_action_distribution(batch, noise=noise)
            return prediction.normalized.mean[:, prediction.action_steps]  # (B, n_action_steps, A)
        batch = self._observe(batch)
        steps = self.config.horizon - self.config.n_obs_steps + 1  # a longer delay commits the whole chunk
        prefix = committed_prefix(prev_chunk_left_over, min(int(inference_delay), steps))
        self._new_prediction = True
        if prefix is not None and self.config.rtc_score == "free":  # the unconstrained belief, gated at once
            score = self.predict_action_distribution(batch, noise=noise).score
            self._update_ood_gates(score)
            prediction = self.predict_action_distribution(batch, noise=noise, prefix=prefix)
            self.last_prediction = replace(prediction, score=score)
        else:
            prediction = self.predict_action_distribution(batch, noise=noise, prefix=prefix)
            self._update_ood_gates(prediction.score)
        return self._hold_where_released(prediction.normalized.mean[:, -steps:], batch)  # (B, steps, A)

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], noise: Tensor | None = None) -> Tensor:
        """One action per call with LeRobot's diffusion queue semantics (see `DiffusionPolicy.select_action`).

        A new chunk is predicted when the action queue is empty: every member samples, the mean of the
        `n_action_steps` executed steps fills the queue, and `self.last_prediction` holds the statistics.
        """
        batch = self._observe(batch)
        self._new_prediction = len(self._queues[ACTION]) == 0
        if self._new_prediction:
            actions = self.predict_action_chunk(batch, noise=noise)  # (B, n_action_steps, A)
            self._queues[ACTION].extend(actions.transpose(0, 1))
            self._update_ood_gates(self.last_prediction.score)

        action = self._queues[ACTION].popleft()  # (B, A)
        return self._hold_where_released(action[:, None], batch)[:, 0]

    def _observe(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """`batch` without its action and with its stacked images, added to the observation queues."""
        batch = dict(batch)  # shallow copy so that adding a key doesn't modify the original
        batch.pop(ACTION, None)
        if self.config.image_features:
            batch[OBS_IMAGES] = torch.stack([batch[key] for key in self.config.image_features], dim=-4)
        self._queues = populate_queues(self._queues, batch)
        return batch

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path, **kwargs):
        """LeRobot's loading, then the gate's calibration and the state normalization from the directory.

        With `ood.enforce=true` a missing calibration is an error that says how to calibrate; without it a
        calibration is loaded when present (so the gate reports its decisions) and skipped otherwise.
        """
        policy = super().from_pretrained(pretrained_name_or_path, **kwargs)
        directory = Path(pretrained_name_or_path)
        if not directory.is_dir():
            if policy.config.ood.enforce:
                raise ValueError(
                    f"`ood.enforce=true` needs a local policy directory with a calibration; {directory} is not "
                    "one. Download the policy and run `lerobot-suture calibrate --policy.path=DIR` on it."
                )
            return policy
        if policy.config.ood.enforce or (directory / policy.config.ood.calibration_file).is_file():
            policy.load_ood_calibration(directory)
        if not bool(torch.isfinite(policy.state_unnormalize_scale).all()):
            stats = saved_normalizer_stats(directory)
            if stats is not None and OBS_STATE in stats:
                policy.set_state_normalization(stats)
        return policy

    # ---- loading ------------------------------------------------------------------------------------

    @classmethod
    def _load_as_safetensor(cls, model, model_file: str, map_location: str, strict: bool):
        check_checkpoint_matches(model, model_file)
        load_model_as_safetensor(
            model, model_file, strict=True, device=resolve_safetensors_device(map_location)
        )
        model._apply_given_action_affine()
        model.invalidate_fused_cache()
        return model
