"""Run a policy in the suture env with the O.O.D. gate at the env step, and hand over to a surgeon.

Every control step the policy (through :class:`~lerobot_suture.policy_runner.PolicyRunner`) proposes
an action and its gate reports the uncertainty score, the threshold and the decision. While the gate
holds control with the policy, the policy's action is executed. Once an enforced gate releases
control (the policy then returns a hold action), a surgeon stand-in takes over:

- ``none``: nobody; the arm holds its pose and waits;
- ``expert``: the scripted expert, reading privileged state, finishes the task from where it is.

With the gate in reporting mode (``ood.enforce=false``, the paper's experiments) the policy keeps
control and the decisions are only logged. Whatever reaches the robot goes through the env's step,
so a CBF wrapper around the env filters the surgeon's actions too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import gymnasium as gym
import numpy as np

from lerobot_suture.expert import ScriptedExpert
from lerobot_suture.registration import MAX_EPISODE_STEPS

SURGEONS = ("none", "expert")
POLICY, SURGEON, HOLD = "policy", "surgeon", "hold"


@dataclass
class StepLog:
    """One control step: who acted, and what the gate and the env said."""

    score: float
    threshold: float
    ood: bool
    released: bool
    new_prediction: bool
    controller: str
    perturbed: bool
    needle_in_tissue: bool
    h: float = math.nan
    cbf_active: bool = False
    cbf_intervened: bool = False


@dataclass
class EpisodeLog:
    seed: int
    scenario: str
    success: bool = False
    steps: list[StepLog] = field(default_factory=list)
    handover_step: int | None = None
    tissue_strain: float = 0.0
    h_min_physics: float = math.nan

    @property
    def scores(self) -> np.ndarray:
        return np.array([s.score for s in self.steps])

    @property
    def onset_step(self) -> int | None:
        return next((k for k, s in enumerate(self.steps) if s.perturbed), None)

    @property
    def first_alarm_step(self) -> int | None:
        return next((k for k, s in enumerate(self.steps) if s.ood), None)

    @property
    def autonomous_success(self) -> bool:
        return self.success and self.handover_step is None


def rollout_episode(
    env: gym.Env,
    runner,
    seed: int,
    surgeon: str = "none",
    max_steps: int | None = None,
) -> EpisodeLog:
    """One episode of ``runner`` (a :class:`PolicyRunner`) in ``env`` with the surgeon stand-in.

    ``env`` may be wrapped in a :class:`~lerobot_suture.safety.cbf_wrapper.CBFActionWrapper`; when it
    records the needle tip's physics-rate trace, ``h_min_physics`` is the smallest barrier value over
    every physics step while the CBF was active.
    """
    if surgeon not in SURGEONS:
        raise ValueError(f"`surgeon` must be one of {SURGEONS}. Got {surgeon!r}.")
    u = env.unwrapped
    if max_steps is None:
        max_steps = (
            env.spec.max_episode_steps if env.spec and env.spec.max_episode_steps else MAX_EPISODE_STEPS
        )
    observation, info = env.reset(seed=seed)
    runner.reset()
    expert = ScriptedExpert()
    log = EpisodeLog(seed=seed, scenario=u.scenario.config.name)
    h_physics: list[float] = []
    for _ in range(max_steps):
        if log.handover_step is None:
            action = runner.act(observation)
            status = runner.policy.ood_status(0)
            controller = POLICY
            if status["released"]:
                log.handover_step = len(log.steps)
                expert.reset(env)  # the expert works out where the task stands
        else:
            status = {**status, "new_prediction": False}  # the released policy is not asked again
        if log.handover_step is not None:
            # Released: the arm holds the pose of the release (the policy's last action), or the surgeon acts.
            if surgeon == "expert":
                action, controller = expert.act(env), SURGEON
            else:
                controller = HOLD
        observation, _, terminated, truncated, info = env.step(action)
        log.steps.append(
            StepLog(
                score=status["score"],
                threshold=status["threshold"],
                ood=status["decision"],
                released=status["released"],
                new_prediction=status["new_prediction"],
                controller=controller,
                perturbed=bool(info["perturbed"]),
                needle_in_tissue=bool(info["needle_in_tissue"]),
                h=float(info.get("h", math.nan)),
                cbf_active=bool(info.get("cbf_active", False)),
                cbf_intervened=bool(info.get("cbf_intervened", False)),
            )
        )
        if info.get("cbf_active") and "needle_tip_trace" in info:
            h_physics.append(_h_min_of_trace(env, info["needle_tip_trace"]))
        if terminated or truncated:
            break
    log.success = bool(info["is_success"])
    log.tissue_strain = float(info["tissue_strain"])
    log.h_min_physics = min(h_physics, default=math.nan)
    return log


def _h_min_of_trace(env: gym.Env, trace: np.ndarray) -> float:
    from lerobot_suture.safety.cbf import ellipsoid_h

    center, axes, rotation = env.get_wrapper_attr("safe_set")()
    return float(np.min(ellipsoid_h(trace, center, axes, rotation)))
