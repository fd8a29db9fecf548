"""A policy trained on relative actions hands out absolute targets: its post-processor composes each predicted
action with the jaw's measured pose.

A dataset recorded with ``lerobot-suture record --relative_actions=true`` stores each action as the step's
motion from the jaw's measured pose, in the jaw frame (``lerobot_suture.sim.relative_actions``). A policy
trained on it learns those motions; what the env, the robot and the CBF take is the absolute target. LeRobot's
own relative actions (``RelativeActionsProcessorStep`` / ``AbsoluteActionsProcessorStep``, pi0's) subtract
the state, which a rotation cannot be; the pair here keeps LeRobot's wiring (the pre-processor caches the
state, the post-processor reads it, ``make_pre_post_processors`` reconnects them when a checkpoint is loaded)
and composes in SE(3) instead. So the checkpoint carries its own action space: ``lerobot-eval``,
``lerobot-rollout``, the leaderboard and the chain run it on the plain env, with no flag to remember.

Each label is relative to the pose measured at its own step, and the pre-processor runs on every step's
observation, so the action executed now is composed with the pose measured now.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from lerobot.lerobot_types import EnvTransition, TransitionKey
from lerobot.processor import ProcessorStepRegistry
from lerobot.processor.relative_action_processor import (
    AbsoluteActionsProcessorStep,
    RelativeActionsProcessorStep,
)

from lerobot_suture.sim.geometry import POSE_DIM
from lerobot_suture.sim.relative_actions import measured_jaw, target_from_relative


def state_cache_step() -> RelativeActionsProcessorStep:
    """The pre-processor step that caches ``observation.state`` (the measured jaw pose) and changes nothing."""
    return RelativeActionsProcessorStep(enabled=False)


def targets_from_relative(measured: np.ndarray, relative: np.ndarray) -> np.ndarray:
    """(B, 10) float64 absolute targets of ``relative`` (B, 10) actions from ``measured`` (B, 10) jaw poses
    (``agent_pos``'s layout: position m, rotation columns, jaw)."""
    return np.stack(
        [target_from_relative(*measured_jaw(pose), a) for pose, a in zip(measured, relative, strict=True)]
    )


@ProcessorStepRegistry.register("jaw_frame_absolute_actions")
@dataclass
class JawFrameAbsoluteActionsStep(AbsoluteActionsProcessorStep):
    """Post-processor step: a relative action (B, 10), unnormalized, becomes its absolute target (B, 10) from
    the jaw pose the paired :func:`state_cache_step` saw last (see the module docstring)."""

    enabled: bool = True

    def __call__(self, transition: EnvTransition) -> EnvTransition:
        if not self.enabled:
            return transition
        action = transition.get(TransitionKey.ACTION)
        if action is None:
            return transition
        state = None if self.relative_step is None else self.relative_step.get_cached_state()
        if state is None:
            raise RuntimeError(
                "This policy outputs actions relative to the jaw's measured pose, and its post-processor has no "
                "pose to compose them with: run its pre-processor on the observation first, and load both with "
                "lerobot.policies.factory.make_pre_post_processors, which pairs them."
            )
        if action.ndim != 2 or action.shape[-1] != POSE_DIM:
            raise ValueError(
                f"A relative policy's actions are composed one step at a time, with the pose measured at that "
                f"step; got a tensor of shape {tuple(action.shape)}, expected (batch, {POSE_DIM}). Execute "
                "the policy's actions one per step (select_action), not as a whole chunk."
            )
        measured = state.detach().to("cpu", torch.float64).reshape(-1, state.shape[-1]).numpy()
        if measured.shape[0] != action.shape[0]:
            raise ValueError(
                f"The pre-processor saw {measured.shape[0]} observations and the policy returned "
                f"{action.shape[0]} actions: run both on the same batch."
            )
        relative = action.detach().to("cpu", torch.float64).numpy()
        targets = torch.from_numpy(targets_from_relative(measured, relative))
        out = transition.copy()
        out[TransitionKey.ACTION] = targets.to(device=action.device, dtype=action.dtype)
        return out
