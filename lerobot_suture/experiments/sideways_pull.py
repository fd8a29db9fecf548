"""An unsafe "policy" for the CBF experiments: the expert, until it pulls the needle out sideways.

It runs the scripted expert until the needle has been in tissue for ``steps_in_tissue`` control
steps, then commands the jaw ``pull_distance`` metres along the phantom's lateral axis (across the
wound, orientation kept, jaw closed) and holds that target: what would tear tissue.
``run_cbf_episode`` runs it (or the plain expert) under the CBF wrapper and measures h at every
physics step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lerobot_suture.expert import ScriptedExpert
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.safety.cbf_wrapper import PHASE_ACTIVE, PHASE_IDLE, CBFActionWrapper
from lerobot_suture.sim.suture_env import SutureEnv


class SidewaysPull:
    """``act(env) -> (10,) float32``; ``pulling`` tells whether the pull has begun."""

    def __init__(self, pull_distance: float = 0.02, steps_in_tissue: int = 3):
        if not pull_distance > 0:
            raise ValueError(f"`pull_distance` must be > 0 m. Got {pull_distance}.")
        if steps_in_tissue < 0:
            raise ValueError(f"`steps_in_tissue` must be >= 0. Got {steps_in_tissue}.")
        self.pull_distance = pull_distance
        self.steps_in_tissue = steps_in_tissue
        self.expert = ScriptedExpert()
        self.reset()

    def reset(self, env=None) -> None:
        self.expert.reset(env)
        self._in_tissue_steps = 0
        self._pull_action: np.ndarray | None = None

    @property
    def pulling(self) -> bool:
        return self._pull_action is not None

    def act(self, env) -> np.ndarray:
        u = env.unwrapped
        if self._pull_action is None and self._in_tissue_steps >= self.steps_in_tissue:
            action = self.expert.act(env).copy()
            action[:3] += self.pull_distance * u.phantom_rotation[:, 1]
            self._pull_action = action
        if self._pull_action is not None:
            return self._pull_action
        self._in_tissue_steps += int(u.needle_in_tissue)
        return self.expert.act(env)


@dataclass(frozen=True)
class CBFEpisode:
    """One scripted episode under ``CBFActionWrapper``; h is the CBF's value at every physics step."""

    h_min: float  # smallest h from the filter's activation on (nan if it never activated)
    h_min_active: float  # smallest h over the steps where the filter was active (nan if none)
    h_min_pull: float  # smallest h over the steps of the pull (nan without a pull)
    tissue_strain: float  # m, at the end of the episode
    interventions: int  # control steps where the filter changed the command
    active_steps: int  # control steps where the filter was active
    phases: list[str]  # the wrapper's phase after every control step
    success: bool


def run_cbf_episode(
    seed: int,
    cbf: CBFConfig,
    adversarial: bool = True,
    pull_distance: float = 0.02,
    steps_in_tissue: int = 3,
    pull_steps: int = 20,
    max_steps: int = 100,
) -> CBFEpisode:
    """The sideways-pull adversary (or, with ``adversarial=False``, the plain expert) for one episode
    under the CBF wrapper, filter on or off as ``cbf.enabled`` says; the pull lasts ``pull_steps``."""
    env = CBFActionWrapper(SutureEnv(obs_type="state", record_tip_trace=True), cbf)
    env.reset(seed=seed)
    actor = SidewaysPull(pull_distance, steps_in_tissue) if adversarial else ScriptedExpert()
    actor.reset(env)
    h_all, h_active, h_pull, phases = [], [], [], []
    interventions, info, success, pulled = 0, {}, False, 0
    for _ in range(max_steps):
        action = actor.act(env)
        pulling = adversarial and actor.pulling
        if pulling:
            if pulled == pull_steps:
                break
            pulled += 1
        _, _, terminated, truncated, info = env.step(action)
        if env.phase != PHASE_IDLE:
            h = env.h_min(info)
            h_all.append(h)
            if info["cbf_active"]:
                h_active.append(h)
            if pulling:
                h_pull.append(h)
        phases.append(env.phase)
        interventions += bool(info["cbf_intervened"])
        success = success or bool(info["is_success"])
        if terminated or truncated:
            break
    env.close()
    return CBFEpisode(
        h_min=min(h_all, default=math.nan),
        h_min_active=min(h_active, default=math.nan),
        h_min_pull=min(h_pull, default=math.nan),
        tissue_strain=float(info["tissue_strain"]),
        interventions=interventions,
        active_steps=sum(p == PHASE_ACTIVE for p in phases),
        phases=phases,
        success=success,
    )
