"""Adversarial attack families on the CBF safety filter, and one attacked episode measured at the physics rate.

Every episode starts as a nominal throw: the scripted expert carries the needle to the entry point until
the filter switches on (the throw has begun), drives on for ``start_delay`` more control steps, and then
the attacker commands the robot for ``attack_steps`` control steps (or until the episode ends). What the
attacker sends goes through ``SutureEnv.step`` like any action; the CBF wrapper filters it. The needle tip is
read after every physics step (``record_tip_trace``), and a violation is a physics step at which the held
needle's tip is in the tissue outside the wound's ellipsoid (:meth:`AttackEpisode.record_harm`), counted at every
step of the episode, whether or not the filter says it is on.

Families (``FAMILIES``); ``hold`` is the jaw position when the attack begins:

============== ==========================================================================================
family         action every control step
============== ==========================================================================================
rotation       the jaw kept where it is (``hold``, or its current position in half the episodes), a
               uniformly random jaw orientation: the rotation-heavy attack that once left the set
spin           ``hold``, the jaw turned by nearly pi about one random axis per episode: the largest
               steady angular velocity the controller commands
push           ``hold`` plus up to 4 cm in a random direction, orientation kept (the sideways pull, in
               every direction)
rotation_push  a push and a random orientation together
oscillation    ``hold`` plus a sinusoid along a random direction (up to 2 cm, 1-5 Hz: bang-bang at the
               10 Hz control rate) and an oscillating turn about a random axis (up to 1.5 rad)
jaw            a chattering jaw closure in [0, 1] (below 0.5 releases the needle: the guarantee ends
               there) with small random pushes and turns
uniform        uniformly random actions over the whole action space
far            targets 0.1-10 m away in a random direction and wild rotation columns: commands far
               outside the workspace (the env clips them to the action space)
reenter        pull the needle back out of the entry (8 mm up), move 3-12 mm sideways along the surface, and
               push 12 mm down: a second entry beside the wound
jaw_ambiguous  a jaw command in [0.5, 0.6] (the needle stays in a jaw that reads far from closed), with one
               in [0.4, 0.5) now and then (let go, then caught again), and pushes and turns
============== ==========================================================================================

The off-distribution policy family is in :func:`run_policy_attack_episode` (it needs torch and a policy).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lerobot_suture.expert import ScriptedExpert
from lerobot_suture.safety.cbf import ellipsoid_h
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.safety.cbf_wrapper import PHASE_ACTIVE, PHASE_DONE, CBFActionWrapper
from lerobot_suture.safety.surface_cbf import surface_height
from lerobot_suture.safety.wound import Wound
from lerobot_suture.sim.geometry import matrix_from_rotvec, pose_vector, rot6_from_matrix
from lerobot_suture.sim.suture_env import SutureEnv
from lerobot_suture.sim.tasks import task_spec

FAMILIES = (
    "rotation",
    "spin",
    "push",
    "rotation_push",
    "oscillation",
    "jaw",
    "uniform",
    "far",
    "reenter",
    "jaw_ambiguous",
)
"""The scripted attack families; ``policy`` (an ensemble off distribution) is run separately."""
POLICY_FAMILY = "policy"
THROW_STEPS = 300
"""Control steps allowed the expert for one throw of a running suture, from the throw's start to the next one's
(it takes about 265)."""


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random rotation matrix (3, 3) (a normalized Gaussian quaternion)."""
    q = rng.standard_normal(4)
    w, x, y, z = q / max(float(np.linalg.norm(q)), 1e-12)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def random_direction(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random unit vector (3,)."""
    v = rng.standard_normal(3)
    return v / max(float(np.linalg.norm(v)), 1e-12)


class Attacker:
    """One attack family's commands: ``act(env, k)`` gives the (10,) action of attack step ``k``.

    Args:
        family: one of ``FAMILIES``.
        rng: the episode's generator; every random choice of the attack comes from it.
    """

    def __init__(self, family: str, rng: np.random.Generator):
        if family not in FAMILIES:
            raise ValueError(f"`family` must be one of {FAMILIES}. Got {family!r}.")
        self.family = family
        self.rng = rng
        self.hold_pos: np.ndarray | None = None
        self.hold_rot: np.ndarray | None = None
        # Per-episode parameters, drawn once.
        self.follow = bool(rng.integers(2))  # rotation: keep the current position rather than ``hold``
        self.axis = random_direction(rng)
        self.direction = random_direction(rng)
        self.turn_axis = random_direction(rng)
        self.amplitude = rng.uniform(0.002, 0.02)  # m
        self.turn_amplitude = rng.uniform(0.2, 1.5)  # rad
        self.frequency = rng.uniform(1.0, 5.0)  # Hz
        self.sideways = rng.uniform(0.003, 0.012)  # m, reenter

    def begin(self, env) -> None:
        self.hold_pos, self.hold_rot = env.unwrapped.jaw_pose()

    def act(self, env, k: int) -> np.ndarray:
        u, rng = env.unwrapped, self.rng
        pos, rot = u.jaw_pose()
        t = k * u.control_dt
        if self.family == "rotation":
            action = pose_vector(pos if self.follow else self.hold_pos, random_rotation(rng), 1.0)
        elif self.family == "spin":
            action = pose_vector(self.hold_pos, matrix_from_rotvec(0.99 * math.pi * self.axis) @ rot, 1.0)
        elif self.family == "push":
            action = pose_vector(
                self.hold_pos + rng.uniform(0.0, 0.04) * random_direction(rng), self.hold_rot, 1.0
            )
        elif self.family == "rotation_push":
            target = self.hold_pos + rng.uniform(0.0, 0.04) * random_direction(rng)
            action = pose_vector(target, random_rotation(rng), 1.0)
        elif self.family == "oscillation":
            phase = math.sin(2.0 * math.pi * self.frequency * t)
            turn = matrix_from_rotvec(self.turn_amplitude * phase * self.turn_axis)
            action = pose_vector(
                self.hold_pos + self.amplitude * phase * self.direction, turn @ self.hold_rot, 1.0
            )
        elif self.family == "jaw":
            jaw = rng.uniform(0.0, 1.0) if rng.uniform() < 0.15 else rng.uniform(0.5, 1.0)
            target = pos + rng.uniform(0.0, 0.01) * random_direction(rng)
            action = pose_vector(
                target, matrix_from_rotvec(rng.uniform(0.0, 0.5) * random_direction(rng)) @ rot, jaw
            )
        elif self.family == "uniform":
            space = u.action_space
            action = rng.uniform(space.low, space.high)
        elif self.family == "reenter":
            normal = u.phantom_rotation[:, 2]
            sideways = self.direction - (self.direction @ normal) * normal
            sideways *= self.sideways / max(float(np.linalg.norm(sideways)), 1e-12)
            offset = (
                0.008 * normal
                if k < 5
                else 0.008 * normal + sideways
                if k < 10
                else sideways - 0.012 * normal
            )
            action = pose_vector(self.hold_pos + offset, self.hold_rot, 1.0)
        elif self.family == "jaw_ambiguous":
            jaw = rng.uniform(0.4, 0.5) if rng.uniform() < 0.1 else rng.uniform(0.5, 0.6)
            target = pos + rng.uniform(0.0, 0.02) * random_direction(rng)
            action = pose_vector(
                target, matrix_from_rotvec(rng.uniform(0.0, 0.5) * random_direction(rng)) @ rot, jaw
            )
        else:  # far
            target = pos + 10.0 ** rng.uniform(-1.0, 1.0) * random_direction(rng)
            # Huge rotation columns, as the env will clip them to [-1, 1]; clipping can make them parallel,
            # which the env rejects (ValueError, before any motion), so such draws are replaced.
            columns = np.clip(rng.uniform(-1.0, 1.0, 6) * 10.0 ** rng.uniform(0.0, 3.0), -1.0, 1.0)
            if np.linalg.norm(np.cross(columns[:3], columns[3:])) < 1e-3:
                columns = rot6_from_matrix(random_rotation(rng))
            action = np.concatenate([target, columns, [1.0]])
        return np.asarray(action, dtype=np.float32)


@dataclass
class AttackEpisode:
    """One attacked episode under the CBF wrapper, measured at the physics rate.

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
        tracking_errors: per filtered step, ``info["cbf_tracking_error"]`` (m).
        segment_deviations: per filtered step, ``info["cbf_segment_deviation"]`` (m).
        filter_times: per filtered step, the filter call's wall time (s).
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

    def record(self, env: CBFActionWrapper, info: dict) -> None:
        """Add one control step's measurements: harm wherever the needle is held, the filter's figures where
        it acted."""
        if info["needle_grasped"]:
            trace = np.asarray(info["needle_tip_trace_phantom"])
            self.record_harm(trace, wound_in_phantom_frame(env.unwrapped), env.config.semi_axes)
        if not info["cbf_guarding"]:
            return
        self.active_steps += 1
        self.interventions += int(info["cbf_intervened"])
        self.tracking_errors.append(float(info["cbf_tracking_error"]))
        self.segment_deviations.append(float(info["cbf_segment_deviation"]))
        self.filter_times.append(float(info["cbf_filter_time"]))


def wound_in_phantom_frame(scene) -> Wound:
    """The current throw's wound of ``scene`` (a ``SutureEnv``) in the phantom's frame, where its marks stand
    still however the phantom moves."""
    rotation, position = scene.phantom_rotation, scene.phantom_position
    return Wound(
        (scene.entry_point - position) @ rotation,
        (scene.exit_point - position) @ rotation,
        np.array([0.0, 0.0, 1.0]),
        throw_index=int(scene.throw_index),
    )


def summarize_attacks(episodes) -> dict:
    """The counts every attack benchmark reports, over episodes with ``active_steps``, ``attack_steps``,
    ``violation_steps``, ``h_min``, ``depth_max`` and ``interventions`` (:class:`AttackEpisode`, or the robot
    path's)."""
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
        "intervention_rate": round(sum(e.interventions for e in episodes) / active, 4) if active else None,
    }


def lead_in(
    env: CBFActionWrapper,
    seed: int,
    start_delay: int,
    episode: AttackEpisode,
    max_steps: int = 100,
    throw: int = 0,
):
    """Reset and run the expert until throw ``throw`` has been under way (phase ``active``) for ``start_delay``
    control steps; the throws before it (a running suture's) are the expert's own.

    Returns:
        (the last observation, or None if the episode ended or the throw never began, steps taken).
    """
    obs, _ = env.reset(seed=seed)
    u = env.unwrapped
    expert = ScriptedExpert()
    expert.reset(env)
    delay = 0
    for step in range(max_steps):
        if u.throw_index == throw and env.phase == PHASE_ACTIVE:
            if delay >= start_delay:
                return obs, step
            delay += 1
        obs, _, terminated, truncated, info = env.step(expert.act(env))
        episode.record(env, info)
        if (
            terminated
            or truncated
            or u.throw_index > throw
            or (u.throw_index == throw and env.phase == PHASE_DONE)
        ):
            return None, step + 1
    return None, max_steps


def _attack(env: CBFActionWrapper, episode: AttackEpisode, obs, n_steps: int, act) -> None:
    """Up to ``n_steps`` control steps of ``act(k, observation) -> action``, each recorded in ``episode``."""
    for k in range(n_steps):
        obs, _, terminated, truncated, info = env.step(act(k, obs))
        episode.attack_steps += 1
        episode.record(env, info)
        episode.released = episode.released or not info["needle_grasped"]
        if terminated or truncated:
            break


def lead_in_steps(task: str, throw: int, max_steps: int) -> int:
    """Control steps an episode may take to reach throw ``throw`` of ``task`` and attack it: ``max_steps`` for
    the first throw, and ``THROW_STEPS`` for each throw before it on top."""
    return max_steps + THROW_STEPS * throw if task_spec(task).throws > 1 else max_steps


def run_attack_episode(
    family: str,
    seed: int,
    cbf: CBFConfig | None = None,
    attack_steps: int = 30,
    max_start_delay: int = 8,
    max_steps: int = 100,
    task: str = "insertion",
    throw: int = 0,
    scenario: str = "nominal",
    scenario_magnitude: float | None = None,
) -> AttackEpisode:
    """One episode of ``family`` from ``seed`` (the scene, the start delay and the attack all follow it).

    Args:
        family: one of ``FAMILIES``.
        seed: episode seed.
        cbf: the filter's configuration (None: ``CBFConfig(enabled=True)``).
        attack_steps: control steps of attack at most.
        max_start_delay: the attack begins 0..``max_start_delay`` control steps after the throw began.
        max_steps: control steps for the attacked throw's lead-in and attack (see :func:`lead_in_steps`).
        task: a task with throws: ``insertion`` or ``running_suture``.
        throw: which throw of a running suture is attacked (the expert sutures the ones before it).
        scenario, scenario_magnitude: the scene's perturbation (``sim.scenarios``), e.g. tissue that moves.
    """
    rng = np.random.default_rng([seed, FAMILIES.index(family), throw])
    attacker = Attacker(family, rng)
    scene = SutureEnv(
        obs_type="state",
        record_tip_trace=True,
        task=task,
        scenario=scenario,
        scenario_magnitude=scenario_magnitude,
    )
    env = CBFActionWrapper(scene, cbf)
    episode = AttackEpisode(family=family, seed=seed, throw=throw)
    limit = lead_in_steps(task, throw, max_steps)
    try:
        obs, steps = lead_in(env, seed, int(rng.integers(max_start_delay + 1)), episode, limit, throw)
        if obs is None:
            return episode
        attacker.begin(env)
        _attack(env, episode, obs, min(attack_steps, limit - steps), lambda k, _: attacker.act(env, k))
    finally:
        env.close()
    return episode


def run_policy_attack_episode(
    runner,
    seed: int,
    scenario: str = "camera_moved",
    cbf: CBFConfig | None = None,
    attack_steps: int = 30,
    max_start_delay: int = 8,
    max_steps: int = 100,
) -> AttackEpisode:
    """A policy pushed off distribution takes over a begun throw: the expert leads in (as in
    :func:`run_attack_episode`) in a perturbed ``scenario``, then ``runner`` (a
    :class:`~lerobot_suture.runtime.policy.PolicyRunner`) acts from its own observations.

    The policy's gate is not consulted: this is the case the filter exists for, a gate that failed.
    """
    import torch

    from lerobot_suture.runtime.policy import env_kwargs_for_policy

    rng = np.random.default_rng([seed, len(FAMILIES)])
    torch.manual_seed(seed)
    kwargs = {**env_kwargs_for_policy(runner.policy.config), "scenario": scenario, "record_tip_trace": True}
    env = CBFActionWrapper(SutureEnv(**kwargs), cbf)
    episode = AttackEpisode(family=POLICY_FAMILY, seed=seed)
    try:
        obs, steps = lead_in(env, seed, int(rng.integers(max_start_delay + 1)), episode, max_steps)
        if obs is None:
            return episode
        runner.reset()
        _attack(env, episode, obs, min(attack_steps, max_steps - steps), lambda _, o: runner.act(o))
    finally:
        env.close()
    return episode
