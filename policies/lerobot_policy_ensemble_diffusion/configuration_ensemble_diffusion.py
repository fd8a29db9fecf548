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
"""Configuration of the ensemble of diffusion policies ("Safe Uncertainty-Aware Learning of Robotic Suturing").

`EnsembleDiffusionConfig` subclasses LeRobot's `DiffusionConfig`, so every member setting (`horizon`,
`down_dims`, `noise_scheduler_type`, ...) keeps its LeRobot name, default handling and validation and is set
from the command line exactly as for `--policy.type=diffusion` (e.g. `--policy.horizon=8`). Only the
defaults that the paper fixes are overridden here; the ensemble, uncertainty and gate settings are added.
"""

import copy
import math
from dataclasses import dataclass, field, fields

from lerobot.configs import PreTrainedConfig
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

from .optim import FusedAdamConfig, FusedAdamWConfig

UNCERTAINTY_SCORES = ("max_abs_cov", "trace", "logdet")
UNCERTAINTY_SPACES = ("normalized", "unnormalized")
UNCERTAINTY_SOURCES = ("total", "epistemic", "aleatoric")
UNCERTAINTY_STEPS = ("horizon", "action")
# The config fields that choose how a prediction is scored, and their allowed values.
SCORE_CHOICES = {
    "uncertainty_score": UNCERTAINTY_SCORES,
    "uncertainty_space": UNCERTAINTY_SPACES,
    "uncertainty_source": UNCERTAINTY_SOURCES,
    "uncertainty_steps": UNCERTAINTY_STEPS,
}
OPTIMIZER_NAMES = ("adam", "adamw")
RTC_SCORES = ("inpainted", "free")
NEEDLE_KEYPOINTS_KEY = "observation.needle_keypoints"
"""The dataset feature `lerobot-suture record` writes with the needle's image position (privileged): a training
target of `needle_keypoints_weight`, never a policy input."""


@dataclass
class EnsembleOODConfig:
    """Options of the out-of-distribution gate that reads the ensemble's uncertainty score.

    The gate itself (calibration, likelihood-ratio test, release of control) lives in
    `lerobot_suture/safety/ood/`; this dataclass is where its options live so that they are saved in the
    policy's `config.json` and settable as `--policy.ood.<name>`.

    Args:
        enforce: If False (default, as in the paper's experiments) the score is only reported. If True the
            policy stops commanding motion on the first O.O.D. decision. Requires a calibration file.
        calibration_file: Name of the calibration JSON inside the pretrained policy directory.
    """

    enforce: bool = False
    calibration_file: str = "ood_calibration.json"

    def __post_init__(self):
        if not self.calibration_file or "/" in self.calibration_file or "\\" in self.calibration_file:
            raise ValueError(
                "`ood.calibration_file` must be a plain file name inside the policy directory. "
                f"Got {self.calibration_file!r}."
            )


@PreTrainedConfig.register_subclass("ensemble_diffusion")
@dataclass
class EnsembleDiffusionConfig(DiffusionConfig):
    """Configuration class for EnsembleDiffusionPolicy: N independently initialised LeRobot diffusion policies.

    All fields of `DiffusionConfig` apply to every member (see its docstring for their meaning); the member
    config is derived with `member_config()`. Defaults differ from `DiffusionConfig` only where the paper
    (Table I) fixes them, and in two places that keep training offline and from scratch:
    `pretrained_backbone_weights=None` (nothing is downloaded) and `use_group_norm=True` (GroupNorm instead of
    BatchNorm in a backbone trained from scratch with small batches, as in the original Diffusion Policy).

    Args:
        n_obs_steps: Observation horizon (paper: 4).
        horizon: Prediction horizon T_p (paper: 8). Must be a multiple of `2 ** len(down_dims)`.
        n_action_steps: Action horizon, the number of predicted steps executed per chunk (paper: 4).
        drop_n_last_frames: `horizon - n_action_steps - n_obs_steps + 1`, as in `DiffusionConfig`.
        pretrained_backbone_weights: torchvision weights for the ResNet backbone. None (default): no
            download, the backbone is trained from scratch.
        use_group_norm: Replace BatchNorm by GroupNorm in the backbone.
        vision_backbone_stages: ResNet stages of each member's image backbone kept before the spatial softmax
            (1-4). 4 (default) is LeRobot's encoder, whose map is 1/32 of the image (3 x 3 from the CPU preset's
            72 px); 3 keeps 1/16 (5 x 5), 2 keeps 1/8 (9 x 9). A finer map lets small things in the image,
            such as the needle, steer the keypoints; fewer stages also cost less.
        optimizer_weight_decay: Weight decay (paper: 0.1), decoupled when `optimizer_name="adamw"`.
        scheduler_warmup_steps: Learning-rate warm-up steps (paper: 100).
        n_members: Number of ensemble members N, >= 1. N = 1 is the ensemble's member recipe as a single
            policy (the same target, backbone and K samples): its covariance is the member's own over its
            K >= 2 samples, and its epistemic part is zero (no other member to disagree with).
        member_seeds: Seed of each member's initialisation, one per member. None (default): members are
            initialised one after another from the global torch RNG (seeded by `lerobot-train --seed`),
            which already makes them independent and reproducible.
        prior_scale: Size of each member's randomized prior function (Osband et al. 2018; see `prior.py`), in
            the U-Net output's normalized units: a fixed random MLP of the member's conditioning, times this
            scale, is added to the member's U-Net output. Training fits the rest to the data, so members still
            agree in distribution, while away from the data their priors make them disagree. 0 (default): no
            prior, the paper's ensemble.
        bootstrap: If True, every member trains on its own bootstrap resample (drawn with replacement) of
            each training batch; if False all members see the same batch and differ by initialisation and
            diffusion noise only (the paper's setting).
        batched_inference: Run the members as one fused network (grouped convolutions, stacked weights) at
            inference. False: loop over the members' own `DiffusionModel`s (same results up to float
            rounding, slower, no extra memory for the fused weight copy).
        uncertainty_samples_per_member: K, the number of action chunks each member samples (with different
            diffusion noise) in `select_action`. K = 1 is the paper. The executed action is the mean of all
            N * K chunks, so K > 1 also averages out the diffusion noise of a single draw; and it allows the
            covariance to be split into aleatoric and epistemic parts (law of total covariance).
        uncertainty_score: Scalar score of a prediction's covariance Sigma (T, A, A): "max_abs_cov" (the
            paper's sigma_hat = max_t max_ij |Sigma_t,ij|), "trace" (max_t tr Sigma_t) or "logdet"
            (max_t log det(Sigma_t + logdet_eps * I)).
        uncertainty_space: Action space in which the score is computed: "normalized" (the policy's
            normalized action space, unit-free; default) or "unnormalized" (dataset units).
        uncertainty_source: Which covariance the score reads: "total" (default; with K = 1 this is the
            paper's ensemble covariance), "epistemic" (covariance of the members' means) or "aleatoric"
            (mean of the members' own covariances; needs K > 1).
        uncertainty_steps: Predicted steps the score takes the maximum over: "horizon" (all `horizon`
            predicted steps, the paper's T_p) or "action" (only the `n_action_steps` executed steps).
        covariance_correction: Bessel correction of every covariance estimate (1: unbiased, as `np.cov`;
            0: population). With 0 the total covariance equals the covariance of all N*K samples pooled.
        logdet_eps: Ridge added to Sigma_t before the log-determinant (N samples give a rank <= N - 1
            matrix, whose plain log-determinant is -inf).
        rtc_score: What the gate reads under LeRobot's real-time chunking engine: "inpainted" (the score of
            the executed chunk, over the steps after its committed prefix) or "free" (the score of a second
            prediction on the same observation without the prefix, as the sync engine scores it, read by the
            gate before the inpainted chunk is sampled; the executed chunk stays the inpainted one, and each
            chunk costs two predictions). The members all continue the same committed prefix, which damps
            their disagreement in the steps after it.
        ood: Options of the out-of-distribution gate (see `EnsembleOODConfig`).
        needle_keypoints_weight: Weight of an auxiliary loss that makes every member's image encoder locate the
            needle: a linear head on the member's image features regresses the needle's tip, middle and tail
            in the endoscope image (the dataset's privileged `observation.needle_keypoints`), and its mean
            squared error, times this weight, is added to the diffusion loss. 0 (default): no auxiliary loss,
            the paper's training. Used in training only; inference is unchanged.
        needle_keypoints_dim: Size of that target, taken from the dataset's feature when the policy is built
            (set automatically; saved so that a checkpoint rebuilds its heads).
        optimizer_name: "adamw" (default; decoupled weight decay, as the paper's 0.1 is meant) or "adam"
            (LeRobot's diffusion preset; L2 penalty). Either is built with PyTorch's fused kernel
            (optimizer types `adamw_fused` / `adam_fused`, see `optim.py`).
        action_feature_names: The names of the training dataset's action components, set by LeRobot's
            `make_policy` when the policy is built from a dataset and saved with the checkpoint. The relative
            names `dx` ... `jaw` (`lerobot-suture record --relative_actions=true`) give the policy's processors
            the pair that composes each action with the measured jaw pose (`jaw_frame_actions.py`), so the
            checkpoint hands out absolute targets wherever it runs.
    """

    # Inputs / output structure (paper, Table I).
    n_obs_steps: int = 4
    horizon: int = 8
    n_action_steps: int = 4
    drop_n_last_frames: int = 1  # horizon - n_action_steps - n_obs_steps + 1

    # Vision backbone: trained from scratch, nothing downloads.
    pretrained_backbone_weights: str | None = None
    use_group_norm: bool = True
    vision_backbone_stages: int = 4

    # Training presets (paper, Table I).
    optimizer_weight_decay: float = 0.1
    scheduler_warmup_steps: int = 100

    # Ensemble.
    n_members: int = 5
    member_seeds: list[int] | None = None
    prior_scale: float = 0.0
    bootstrap: bool = False
    batched_inference: bool = True

    # Uncertainty.
    uncertainty_samples_per_member: int = 1
    uncertainty_score: str = "max_abs_cov"
    uncertainty_space: str = "normalized"
    uncertainty_source: str = "total"
    uncertainty_steps: str = "horizon"
    covariance_correction: int = 1
    logdet_eps: float = 1e-6
    rtc_score: str = "inpainted"

    # Out-of-distribution gate.
    ood: EnsembleOODConfig = field(default_factory=EnsembleOODConfig)

    # Auxiliary training target: where the needle is in the image.
    needle_keypoints_weight: float = 0.0
    needle_keypoints_dim: int | None = None

    # Optimizer.
    optimizer_name: str = "adamw"

    # The dataset's action names (LeRobot's field; `make_policy` fills it from the dataset).
    action_feature_names: list[str] | None = None

    def __post_init__(self):
        super().__post_init__()

        if self.n_members < 1:
            raise ValueError(f"`n_members` must be >= 1. Got {self.n_members}.")
        if self.n_members == 1 and (
            self.uncertainty_samples_per_member < 2 or self.uncertainty_source == "epistemic"
        ):
            raise ValueError(
                "A single member (`n_members`=1) has no members to disagree: its covariance needs "
                "`uncertainty_samples_per_member` >= 2 and `uncertainty_source` 'total' or 'aleatoric'. Got "
                f"{self.uncertainty_samples_per_member} and {self.uncertainty_source!r}."
            )
        if self.member_seeds is not None:
            self.member_seeds = [int(s) for s in self.member_seeds]
            if len(self.member_seeds) != self.n_members:
                raise ValueError(
                    f"`member_seeds` must hold one seed per member ({self.n_members}). "
                    f"Got {len(self.member_seeds)}: {self.member_seeds}."
                )
            if len(set(self.member_seeds)) != len(self.member_seeds):
                raise ValueError(
                    f"`member_seeds` must be distinct, or members start identical. Got {self.member_seeds}."
                )
        if self.uncertainty_samples_per_member < 1:
            raise ValueError(
                f"`uncertainty_samples_per_member` must be >= 1. Got {self.uncertainty_samples_per_member}."
            )
        for name, allowed in (
            *SCORE_CHOICES.items(),
            ("optimizer_name", OPTIMIZER_NAMES),
            ("rtc_score", RTC_SCORES),
        ):
            if getattr(self, name) not in allowed:
                raise ValueError(f"`{name}` must be one of {list(allowed)}. Got {getattr(self, name)!r}.")
        if self.uncertainty_source == "aleatoric" and self.uncertainty_samples_per_member < 2:
            raise ValueError(
                "`uncertainty_source`='aleatoric' needs `uncertainty_samples_per_member` >= 2 (the members' own "
                f"covariances need two samples each). Got {self.uncertainty_samples_per_member}."
            )
        if self.covariance_correction not in (0, 1):
            raise ValueError(f"`covariance_correction` must be 0 or 1. Got {self.covariance_correction}.")
        if self.n_members > 1 and self.covariance_correction >= self.n_members:
            raise ValueError(
                f"`covariance_correction` ({self.covariance_correction}) must be < `n_members` ({self.n_members})."
            )
        if not self.logdet_eps > 0:
            raise ValueError(f"`logdet_eps` must be > 0. Got {self.logdet_eps}.")
        if self.n_action_steps > self.horizon - self.n_obs_steps + 1:
            raise ValueError(
                "`n_action_steps` must be <= `horizon - n_obs_steps + 1` "
                f"({self.horizon - self.n_obs_steps + 1}). Got {self.n_action_steps}."
            )
        if self.num_inference_steps is not None and not (
            1 <= self.num_inference_steps <= self.num_train_timesteps
        ):
            raise ValueError(
                f"`num_inference_steps` must be in [1, {self.num_train_timesteps}] (`num_train_timesteps`). "
                f"Got {self.num_inference_steps}."
            )
        if not (math.isfinite(self.needle_keypoints_weight) and self.needle_keypoints_weight >= 0):
            raise ValueError(f"`needle_keypoints_weight` must be >= 0. Got {self.needle_keypoints_weight}.")
        if not (math.isfinite(self.prior_scale) and self.prior_scale >= 0):
            raise ValueError(f"`prior_scale` must be finite and >= 0 (0: no prior). Got {self.prior_scale}.")
        if self.vision_backbone_stages not in (1, 2, 3, 4):
            raise ValueError(
                f"`vision_backbone_stages` must be 1, 2, 3 or 4. Got {self.vision_backbone_stages}."
            )
        if isinstance(self.ood, dict):  # built from Python with a plain dict
            self.ood = EnsembleOODConfig(**self.ood)

    @property
    def relative_actions(self) -> bool:
        """Whether the policy was trained on actions relative to the jaw's measured pose."""
        from lerobot_suture.sim.relative_actions import RELATIVE_ACTION_NAMES

        return (
            self.action_feature_names is not None
            and tuple(self.action_feature_names) == RELATIVE_ACTION_NAMES
        )

    def validate_features(self) -> None:
        """LeRobot's checks, after taking the needle's keypoints out of the inputs.

        A dataset from `lerobot-suture record` holds `observation.needle_keypoints`, which lerobot-train lists
        as an input like every `observation.*` feature. It is privileged (the env does not provide it at
        inference), so it is never an input: only its size is kept, for `needle_keypoints_weight`.
        """
        if self.input_features and NEEDLE_KEYPOINTS_KEY in self.input_features:
            self.needle_keypoints_dim = int(self.input_features.pop(NEEDLE_KEYPOINTS_KEY).shape[0])
        if self.needle_keypoints_weight > 0 and self.needle_keypoints_dim is None:
            raise ValueError(
                f"`needle_keypoints_weight` > 0 needs the dataset feature '{NEEDLE_KEYPOINTS_KEY}', which this "
                "dataset lacks: record it again with `lerobot-suture record` (its image datasets hold it), or "
                "train with `--policy.needle_keypoints_weight=0`."
            )
        super().validate_features()

    def member_config(self) -> DiffusionConfig:
        """The plain LeRobot `DiffusionConfig` of one member (every `DiffusionConfig` field copied)."""
        kwargs = {f.name: copy.deepcopy(getattr(self, f.name)) for f in fields(DiffusionConfig) if f.init}
        return DiffusionConfig(**kwargs)

    @classmethod
    def from_member_config(cls, member: DiffusionConfig, **ensemble_kwargs) -> "EnsembleDiffusionConfig":
        """An ensemble config whose members are `member` (every `DiffusionConfig` field copied)."""
        kwargs = {f.name: copy.deepcopy(getattr(member, f.name)) for f in fields(DiffusionConfig) if f.init}
        kwargs.update(ensemble_kwargs)
        return cls(**kwargs)

    def score_choices(self) -> dict[str, tuple[str, ...]]:
        """The distinct ways this policy can score a prediction: config field -> values. With one sample
        per member only the configured source is listed (`total` and `epistemic` are then equal, and
        `aleatoric` needs two samples). `EnsembleDiffusionPolicy.rescore` takes them.
        """
        choices = dict(SCORE_CHOICES)
        if self.uncertainty_samples_per_member < 2:
            choices["uncertainty_source"] = (self.uncertainty_source,)
        return choices

    def score_settings(self) -> dict:
        """The settings besides the score's name and space that shape its distribution on a given policy.

        The gate's calibration records them, and a policy refuses a calibration fitted with others: a
        threshold fitted at K = 1 sample per member is not one for K = 8, and the per-episode threshold,
        a maximum over the episode's predictions, is not one for another `n_action_steps` (a prediction
        every n steps).
        """
        return {
            "uncertainty_source": self.uncertainty_source,
            "uncertainty_samples_per_member": self.uncertainty_samples_per_member,
            "uncertainty_steps": self.uncertainty_steps,
            "covariance_correction": self.covariance_correction,
            "noise_scheduler_type": self.noise_scheduler_type,
            "num_inference_steps": self.num_inference_steps,
            "n_action_steps": self.n_action_steps,
        }

    def get_optimizer_preset(self) -> FusedAdamConfig | FusedAdamWConfig:
        optimizer_cls = FusedAdamWConfig if self.optimizer_name == "adamw" else FusedAdamConfig
        return optimizer_cls(
            lr=self.optimizer_lr,
            betas=self.optimizer_betas,
            eps=self.optimizer_eps,
            weight_decay=self.optimizer_weight_decay,
        )
