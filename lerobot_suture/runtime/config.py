"""The preamble every command that runs a trained policy shares: where the policy is, which device runs
it, and how many envs are rolled out in lockstep."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class PolicyPathConfig:
    """``--policy.path=DIR``: the ``pretrained_model`` directory of a ``lerobot-train`` checkpoint."""

    path: Path | None = None


@dataclass
class PolicyCommandConfig:
    """Args:
    policy: ``--policy.path=DIR``, the trained policy's ``pretrained_model`` directory (required).
    device: torch device of the policy (``cpu``, ``cuda``, ``cuda:1``, ``mps``).
    """

    policy: PolicyPathConfig = field(default_factory=PolicyPathConfig)
    device: str = "cpu"

    def __post_init__(self):
        if self.policy.path is None:
            raise ValueError(
                "`--policy.path` is required: the pretrained_model directory of a trained policy, e.g. "
                "outputs/train/NAME/checkpoints/last/pretrained_model."
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
