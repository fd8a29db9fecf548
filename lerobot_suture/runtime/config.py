"""The preamble every command that runs a trained policy shares: where the policy is, which device runs
it, and how many envs are rolled out in lockstep."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar


@dataclass
class PolicyPathConfig:
    """``--policy.path=DIR``: the ``pretrained_model`` directory of a ``lerobot-train`` checkpoint.

    Inference approximations, LeRobot's own config fields as ``lerobot-eval`` overrides them (unset: as
    trained): ``--policy.num_inference_steps=S``, fewer DDIM denoising steps; and, for an ensemble,
    ``--policy.uncertainty_samples_per_member=K``, fewer chunks per member. Both change the episodes and
    the gate's scores (``docs/results/benchmarks/eval_approximations.json`` measures both), so a calibrated
    ensemble refuses them at load: ``lerobot-suture calibrate --policy.path=DIR ... --copy_to=COPY`` makes
    a calibrated copy with them.
    """

    path: Path | None = None
    num_inference_steps: int | None = None
    uncertainty_samples_per_member: int | None = None

    def __post_init__(self):
        for name, value in self.overrides.items():
            if value < 1:
                raise ValueError(f"`policy.{name}` must be >= 1 (or unset: as trained). Got {value}.")

    @property
    def overrides(self) -> dict:
        """The set approximations as config overrides (empty: the policy as trained)."""
        chosen = {
            "num_inference_steps": self.num_inference_steps,
            "uncertainty_samples_per_member": self.uncertainty_samples_per_member,
        }
        return {name: value for name, value in chosen.items() if value is not None}


@dataclass
class PolicyCommandConfig:
    """Args:
    policy: ``--policy.path=DIR``, the trained policy's ``pretrained_model`` directory (required).
    device: torch device of the policy (``cpu``, ``cuda``, ``cuda:1``, ``mps``).
    """

    policy: PolicyPathConfig = field(default_factory=PolicyPathConfig)
    device: str = "cpu"

    writes_to_policy: ClassVar[bool] = False
    """A command that writes into the policy's directory (a calibration, a fine-tuned policy) runs it as
    trained: what it writes must hold for the policy as it will be loaded."""

    def __post_init__(self):
        if self.policy.path is None:
            raise ValueError(
                "`--policy.path` is required: the pretrained_model directory of a trained policy, e.g. "
                "outputs/train/NAME/checkpoints/last/pretrained_model."
            )
        if self.writes_to_policy and self.policy.overrides:
            flags = " ".join(f"--policy.{name}" for name in self.policy.overrides)
            settings = " ".join(f"--policy.{name}={value}" for name, value in self.policy.overrides.items())
            raise ValueError(
                f"This command writes into the policy's directory, for the policy as trained: drop {flags}. "
                f"`lerobot-suture calibrate --policy.path={self.policy.path} {settings} --copy_to=COPY` makes "
                "a calibrated copy of the policy with them."
            )
        if self.device.split(":")[0] not in ("cpu", "cuda", "mps", "xpu"):
            raise ValueError(f"`device` must be cpu, cuda[:N], mps or xpu. Got {self.device!r}.")


@dataclass
class RolloutCommandConfig(PolicyCommandConfig):
    """Args:
    batch_envs: envs run in lockstep with one batched policy call per control step, >= 1 (a seed gives
        the same episode at any ``batch_envs``: each episode's noise comes from its own seed).
    workers: processes the batches are spread over, >= 1, each with its own copy of the policy and
        ``cores // workers`` torch threads (on a CPU, one per core is fastest); the same episodes.
    """

    batch_envs: int = 8
    workers: int = 1

    def __post_init__(self):
        super().__post_init__()
        if self.batch_envs < 1:
            raise ValueError(f"`batch_envs` must be >= 1. Got {self.batch_envs}.")
        if self.workers < 1:
            raise ValueError(f"`workers` must be >= 1. Got {self.workers}.")
