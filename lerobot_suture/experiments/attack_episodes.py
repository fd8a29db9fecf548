"""Attacked episodes on either path, harm counted at the physics rate wherever it happens.

Every episode starts as a nominal throw: the scripted expert carries the needle to the entry point until the
throw has begun (the guard's phase ``active``; in a running suture, on the throw attacked, the ones before it
sutured by the expert), drives on for ``start_delay`` more control steps, and then an attacker
(``cbf_attacks.Attacker``) commands the arm for ``attack_steps`` control steps or until the episode ends.

One loop serves both paths through a small adapter (:class:`AttackPath`): :class:`EnvPath` sends every action
through ``SutureEnv.step`` under ``CBFActionWrapper``; the robot plugin's ``RobotPath`` sends it through the robot
action pipeline holding ``suture_cbf`` to ``SutureSim``. On both, the needle tip is read after every physics step
in the phantom's frame, and a violation is a physics step at which the needle, held by the simulator's grasp, has
its tip in the tissue outside the wound's ellipsoid, whatever the filter says of its own state.

Conditions (:data:`CONDITIONS`) name the scene and the arm the attacks meet: tissue that stands still or moves
(within the declared bounds, or beyond them), a running suture's every throw, and the robot path's faults.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple, Protocol

import numpy as np

from lerobot_suture.experiments.cbf_attacks import FAMILIES, POLICY_FAMILY, Attacker
from lerobot_suture.expert import ScriptedExpert
from lerobot_suture.safety.cbf import ellipsoid_h
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.safety.cbf_wrapper import CBFActionWrapper, wound_in_phantom_frame
from lerobot_suture.safety.surface_cbf import surface_height
from lerobot_suture.safety.tip_guard import PHASE_ACTIVE, PHASE_DONE
from lerobot_suture.safety.wound import Wound
from lerobot_suture.sim.scenarios import ScenarioConfig
from lerobot_suture.sim.suture_env import SutureEnv
from lerobot_suture.sim.tasks import task_spec

THROW_STEPS = 300
"""Control steps allowed the expert for one throw of a running suture, from the throw's start to the next one's
(it takes about 265)."""

_BREATHING = 2.0 * math.pi * ScenarioConfig().breathing_frequency
BREATHING_AT_BOUND = CBFConfig().tissue_acceleration_max / _BREATHING**2
"""Breathing amplitude (m) whose peak acceleration is the declared bound (about 8.1 mm, 12.7 mm/s at 0.25 Hz)."""


@dataclass(frozen=True)
class AttackCondition:
    """The scene and the arm the attacks meet.

    Args:
        task: a task with throws (``insertion`` or ``running_suture``; a running suture's throws are attacked
            in turn, ``throw = seed % 4``).
        scenario, scenario_magnitude: the scene's perturbation (``sim.scenarios``), e.g. tissue that moves.
        faults: the robot path's faults (``FaultConfig`` fields); the env path has none.
        within_bounds: the tissue's motion stays within the filter's declared bounds (a bar), or goes beyond
            them (measured: how many episodes are flagged, and how deep any violation goes).
    """

    task: str = "insertion"
    scenario: str = "nominal"
    scenario_magnitude: float | None = None
    faults: dict = field(default_factory=dict)
    within_bounds: bool = True

    def throw(self, seed: int) -> int:
        """The throw attacked in the episode of ``seed``."""
        return seed % task_spec(self.task).throws


CONDITIONS: dict[str, AttackCondition] = {
    "still": AttackCondition(),
    "phantom_servo": AttackCondition(scenario="phantom_servo"),
    "phantom_moved_after_insertion": AttackCondition(scenario="phantom_moved_after_insertion"),
    "breathing_at_bound": AttackCondition(scenario="breathing", scenario_magnitude=BREATHING_AT_BOUND),
    "running_suture": AttackCondition(task="running_suture"),
    "arm_lag_0.1": AttackCondition(faults={"arm_lag": 0.1}),
    "arm_lag_0.2": AttackCondition(faults={"arm_lag": 0.2}),
    "arm_lag_0.3": AttackCondition(faults={"arm_lag": 0.3}),
    "observation_latency_3": AttackCondition(faults={"observation_latency": 3}),
    "command_latency_3": AttackCondition(faults={"command_latency": 3}),
    # A 30 mm glide over 1.5 s peaks at 66 mm/s^2 (the bound is 20); breathing at three times the bound.
    "beyond_bound_moved": AttackCondition(
        scenario="phantom_moved_after_insertion", scenario_magnitude=0.03, within_bounds=False
    ),
    "beyond_bound_breathing": AttackCondition(
        scenario="breathing", scenario_magnitude=3.0 * BREATHING_AT_BOUND, within_bounds=False
    ),
}
"""Every condition the attack benchmark runs; those with ``faults`` on the robot path only."""


def conditions_for(path: str) -> list[str]:
    """The names of :data:`CONDITIONS` that apply to ``path`` (``env`` or ``robot``)."""
    return [name for name, c in CONDITIONS.items() if path == "robot" or not c.faults]


class PathStep(NamedTuple):
    """One control step on a path: the scene's episode is over, its info, and what the guard did."""

    over: bool
    info: dict
    guarding: bool
    intervened: bool
    motion_exceeded: bool


class AttackPath(Protocol):
    """What the episode loop needs of a path: the scene the expert and the attacker read, a reset, one control
    step, and the guard's view of the throw (its phase, and which throw it has registered)."""

    task: str
    semi_axes: np.ndarray

    @property
    def scene(self): ...

    @property
    def phase(self) -> str: ...

    @property
    def throw_index(self) -> int | None: ...

    def reset(self, seed: int) -> None: ...

    def send(self, action: np.ndarray) -> PathStep: ...

    def close(self) -> None: ...


class EnvPath:
    """The env path: ``SutureEnv`` (state observations, physics-rate tip trace) under ``CBFActionWrapper``.

    Args:
        condition: the scene (no ``faults``). cbf: the filter (None: ``CBFConfig(enabled=True)``).
        env_kwargs: more ``SutureEnv`` arguments (a policy's observation type, say).
    """

    def __init__(self, condition: AttackCondition, cbf: CBFConfig | None = None, **env_kwargs):
        if condition.faults:
            raise ValueError(f"faults {condition.faults} are the robot path's; the env path has none.")
        kwargs = {"obs_type": "state", **env_kwargs}
        scene = SutureEnv(
            record_tip_trace=True,
            task=condition.task,
            scenario=condition.scenario,
            scenario_magnitude=condition.scenario_magnitude,
            **kwargs,
        )
        self.env = CBFActionWrapper(scene, cbf)
        self.task = condition.task
        self.semi_axes = self.env.config.semi_axes
        self.observation = None

    @property
    def scene(self) -> CBFActionWrapper:
        return self.env

    @property
    def phase(self) -> str:
        return self.env.phase

    @property
    def throw_index(self) -> int | None:
        return self.env.guard.throw_index

    def reset(self, seed: int) -> None:
        self.observation, _ = self.env.reset(seed=seed)

    def send(self, action: np.ndarray) -> PathStep:
        self.observation, _, terminated, truncated, info = self.env.step(action)
        return PathStep(
            bool(terminated or truncated),
            info,
            bool(info["cbf_guarding"]),
            bool(info["cbf_intervened"]),
            bool(info["cbf_motion_exceeded"]),
        )

    def close(self) -> None:
        self.env.close()


@dataclass
class AttackEpisode:
    """One attacked episode, measured at the physics rate.

    Attributes:
        family, seed, throw: what was run (``throw``: the throw of a running suture attacked).
        active_steps: control steps in which the filter acted (attack and the expert's lead-in).
        attack_steps: control steps the attacker commanded.
        violation_steps: physics steps at which the held needle's tip was in the tissue outside the wound's
            ellipsoid, over the whole episode.
        h_min: smallest ellipsoid barrier h over the physics steps at which the held needle's tip was below
            the tissue surface (nan if it never was): < 0 is a violation.
        depth_max: deepest a violation went below the surface (m), 0 without one.
        interventions: control steps in which the filter changed the command.
        motion_flagged: the guard reported the tissue's motion beyond its declared bounds at some step.
        moved_while_held: the tissue moved at some step in which the needle was held (what a flag needs).
        tracking_errors: per filtered step, ``info["cbf_tracking_error"]`` (m; env path).
        segment_deviations: per filtered step, ``info["cbf_segment_deviation"]`` (m; env path).
        filter_times: per filtered step, the filter call's wall time (s; env path).
        released: the jaw let the needle go during the attack.
    """

    family: str
    seed: int
    throw: int = 0
    active_steps: int = 0
    attack_steps: int = 0
    violation_steps: int = 0
    h_min: float = math.nan
    depth_max: float = 0.0
    interventions: int = 0
    motion_flagged: bool = False
    moved_while_held: bool = False
    tracking_errors: list[float] = field(default_factory=list)
    segment_deviations: list[float] = field(default_factory=list)
    filter_times: list[float] = field(default_factory=list)
    released: bool = False

    def record_harm(self, trace: np.ndarray, wound: Wound, semi_axes: np.ndarray) -> None:
        """Count the physics steps of one control step's tip ``trace`` (n, 3) m, the needle held throughout, at
        which the tip was in the tissue outside ``wound``'s ellipsoid of ``semi_axes`` (3,) m. ``trace`` and
        ``wound`` in one frame: the phantom's, where a moving phantom's wound stands still
        (:func:`wound_in_phantom_frame`, ``info["needle_tip_trace_phantom"]``)."""
        depth = -surface_height(trace, wound.entry_point, wound.surface_normal)
        below = depth > 0.0
        if not below.any():
            return
        center, rotation = wound.ellipsoid_frame()
        h = np.asarray(ellipsoid_h(trace[below], center, semi_axes, rotation))
        violated = h < 0.0
        self.violation_steps += int(np.sum(violated))
        low = float(np.min(h))
        self.h_min = low if math.isnan(self.h_min) else min(self.h_min, low)
        if violated.any():
            self.depth_max = max(self.depth_max, float(np.max(depth[below][violated])))

    def record(self, path: AttackPath, step: PathStep) -> None:
        """Add one control step: harm wherever the needle is held, the filter's figures where it acted."""
        info = step.info
        scene = path.scene.unwrapped
        if info["needle_grasped"]:
            trace = np.asarray(info["needle_tip_trace_phantom"])
            self.record_harm(trace, wound_in_phantom_frame(scene), path.semi_axes)
            self.moved_while_held = self.moved_while_held or scene.scenario.moving
        self.motion_flagged = self.motion_flagged or step.motion_exceeded
        if not step.guarding:
            return
        self.active_steps += 1
        self.interventions += int(step.intervened)
        if "cbf_tracking_error" in info:
            self.tracking_errors.append(float(info["cbf_tracking_error"]))
            self.segment_deviations.append(float(info["cbf_segment_deviation"]))
            self.filter_times.append(float(info["cbf_filter_time"]))


def summarize_attacks(episodes) -> dict:
    """The counts every attack benchmark reports, over :class:`AttackEpisode` s."""
    active = sum(e.active_steps for e in episodes)
    h_mins = [e.h_min for e in episodes if np.isfinite(e.h_min)]
    return {
        "episodes": len(episodes),
        "episodes_active": sum(e.active_steps > 0 for e in episodes),
        "active_steps": active,
        "attack_steps": sum(e.attack_steps for e in episodes),
        "violations": {
            "episodes": sum(e.violation_steps > 0 for e in episodes),
            "physics_steps": sum(e.violation_steps for e in episodes),
        },
        "h_min": round(min(h_mins), 5) if h_mins else None,
        "violation_depth_max_mm": round(max((e.depth_max for e in episodes), default=0.0) * 1e3, 3),
        "moved_while_held_episodes": sum(e.moved_while_held for e in episodes),
        "motion_flagged_episodes": sum(e.motion_flagged for e in episodes),
        "intervention_rate": round(sum(e.interventions for e in episodes) / active, 4) if active else None,
    }


def lead_in_steps(task: str, throw: int, max_steps: int) -> int:
    """Control steps an episode may take to reach throw ``throw`` of ``task`` and attack it: ``max_steps`` for
    the first throw, and ``THROW_STEPS`` for each throw before it on top."""
    return max_steps + THROW_STEPS * throw if task_spec(task).throws > 1 else max_steps


def lead_in(
    path: AttackPath, seed: int, start_delay: int, episode: AttackEpisode, limit: int, throw: int = 0
):
    """Reset and run the expert until throw ``throw`` has been under way for ``start_delay`` control steps,
    as the guard sees it. Returns the control steps taken, or None if the episode ended or the throw never
    began within ``limit``."""
    path.reset(seed)
    expert = ScriptedExpert()
    expert.reset(path.scene)
    delay = 0
    for steps in range(limit):
        if path.throw_index == throw and path.phase == PHASE_ACTIVE:
            if delay >= start_delay:
                return steps
            delay += 1
        step = path.send(expert.act(path.scene))
        episode.record(path, step)
        seen = path.throw_index or 0
        if step.over or seen > throw or (seen == throw and path.phase == PHASE_DONE):
            return None
    return None


def attack(path: AttackPath, episode: AttackEpisode, n_steps: int, act) -> None:
    """Up to ``n_steps`` control steps of ``act(k) -> action``, each recorded in ``episode``."""
    for k in range(n_steps):
        step = path.send(act(k))
        episode.attack_steps += 1
        episode.record(path, step)
        episode.released = episode.released or not step.info["needle_grasped"]
        if step.over:
            break


def run_attack(
    path: AttackPath,
    family: str,
    seed: int,
    throw: int = 0,
    attack_steps: int = 30,
    max_start_delay: int = 8,
    max_steps: int = 100,
) -> AttackEpisode:
    """One episode of ``family`` from ``seed`` on ``path`` (the scene, the start delay and the attack all follow
    the seed), attacking throw ``throw``.

    Args:
        attack_steps: control steps of attack at most.
        max_start_delay: the attack begins 0..``max_start_delay`` control steps after the throw began.
        max_steps: control steps for the attacked throw's lead-in and attack (see :func:`lead_in_steps`).
    """
    rng = np.random.default_rng([seed, FAMILIES.index(family), throw])
    attacker = Attacker(family, rng)
    episode = AttackEpisode(family=family, seed=seed, throw=throw)
    limit = lead_in_steps(path.task, throw, max_steps)
    steps = lead_in(path, seed, int(rng.integers(max_start_delay + 1)), episode, limit, throw)
    if steps is None:
        return episode
    attacker.begin(path.scene)
    attack(path, episode, min(attack_steps, limit - steps), lambda k: attacker.act(path.scene, k))
    return episode


def run_attack_episode(
    family: str, seed: int, condition: str = "still", cbf: CBFConfig | None = None, **kwargs
) -> AttackEpisode:
    """One episode of ``family`` from ``seed`` on the env path in ``condition`` (:data:`CONDITIONS`), the throw
    the condition gives the seed; ``kwargs`` as :func:`run_attack`'s."""
    spec = CONDITIONS[condition]
    path = EnvPath(spec, cbf)
    try:
        return run_attack(path, family, seed, spec.throw(seed), **kwargs)
    finally:
        path.close()


def run_policy_attack(
    runner,
    seed: int,
    scenario: str = "camera_moved",
    cbf: CBFConfig | None = None,
    attack_steps: int = 30,
    max_start_delay: int = 8,
    max_steps: int = 100,
) -> AttackEpisode:
    """A policy pushed off distribution takes over a begun throw on the env path: the expert leads in (as in
    :func:`run_attack`) in a perturbed ``scenario``, then ``runner`` (a
    :class:`~lerobot_suture.runtime.policy.PolicyRunner`) acts from its own observations.

    The policy's gate is not consulted: this is the case the filter exists for, a gate that failed.
    """
    import torch

    from lerobot_suture.runtime.policy import env_kwargs_for_policy

    rng = np.random.default_rng([seed, len(FAMILIES)])
    torch.manual_seed(seed)
    kwargs = dict(env_kwargs_for_policy(runner.policy.config))
    kwargs.pop("record_tip_trace", None)
    path = EnvPath(AttackCondition(scenario=scenario), cbf, **kwargs)
    episode = AttackEpisode(family=POLICY_FAMILY, seed=seed)
    try:
        steps = lead_in(path, seed, int(rng.integers(max_start_delay + 1)), episode, max_steps)
        if steps is None:
            return episode
        runner.reset()
        attack(path, episode, min(attack_steps, max_steps - steps), lambda _: runner.act(path.observation))
    finally:
        path.close()
    return episode
