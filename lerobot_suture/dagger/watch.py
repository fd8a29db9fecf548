"""A surgeon stand-in that watches the policy and takes over on its own when the policy's commands stray.

The gate hands over what the ensemble is unsure of; a policy that is sure and wrong (the phantom moved
under a needle already in tissue) is never handed over, so gated DAgger gets no label there. A surgeon at
the console sees the arm go wrong and takes over (HG-DAgger's human gating). The stand-in does so from the
privileged state: at every step the policy drives, it works out its own action at that state (the
ungated arm's :class:`~lerobot_suture.dagger.labelling.StateLabeller`) and compares the two jaw targets;
after ``patience`` consecutive steps whose targets lie more than ``position`` apart, or turned more than
``angle`` from each other, it takes over and finishes the throw.

The default limits, and the measurement they were chosen from, are in ``docs/surgeon.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lerobot_suture.dagger.labelling import StateLabeller
from lerobot_suture.expert import ExpertConfig, ScriptedExpert
from lerobot_suture.sim.geometry import matrix_from_rot6, rotvec_from_matrix
from lerobot_suture.surgeon.surgeons import ExpertSurgeon


@dataclass(frozen=True)
class WatchConfig:
    """When the gated arm's surgeon stand-in takes over on its own (collection only: the evaluation's
    surgeon takes over only when the gate hands over, so autonomy keeps its meaning).

    Args:
        enabled: the stand-in watches (off: it acts only after the gate's handover).
        position: distance between the policy's jaw target and the expert's above which a step strays (m).
        angle: angle between their jaw orientations above which a step strays (rad).
        patience: consecutive straying steps before the stand-in takes over, >= 1.
    """

    enabled: bool = False
    position: float = 0.0025
    angle: float = 0.15
    patience: int = 3

    def __post_init__(self):
        if not (np.isfinite(self.position) and self.position > 0):
            raise ValueError(f"`watch.position` must be a distance > 0 (m). Got {self.position}.")
        if not (np.isfinite(self.angle) and self.angle > 0):
            raise ValueError(f"`watch.angle` must be an angle > 0 (rad). Got {self.angle}.")
        if self.patience < 1:
            raise ValueError(f"`watch.patience` must be >= 1 (steps). Got {self.patience}.")


def pose_divergence(action: np.ndarray, reference: np.ndarray) -> tuple[float, float]:
    """Distance (m) and angle (rad) between the jaw targets of two (10,) env actions."""
    distance = float(np.linalg.norm(np.asarray(action[:3]) - np.asarray(reference[:3])))
    relative = matrix_from_rot6(np.asarray(action[3:9])).T @ matrix_from_rot6(np.asarray(reference[3:9]))
    return distance, float(np.linalg.norm(rotvec_from_matrix(relative)))


class WatchingExpertSurgeon(ExpertSurgeon):
    """The scripted expert as the surgeon, taking over on its own after ``watch.patience`` straying steps."""

    name = "expert_watching"

    def __init__(self, expert_config: ExpertConfig, watch: WatchConfig):
        super().__init__(ScriptedExpert(expert_config))
        self.watch = watch
        self.labeller = StateLabeller(expert_config)
        self.streak = 0

    def begin_episode(self, env) -> None:
        self.labeller.reset(env)
        self.streak = 0

    def intervenes(self, env, action: np.ndarray) -> bool:
        distance, angle = pose_divergence(action, self.labeller.label(env))
        strays = distance > self.watch.position or angle > self.watch.angle
        self.streak = self.streak + 1 if strays else 0
        return self.streak >= self.watch.patience
