"""The CBF holds whatever the action: attack families, property tests over states and action sequences,
and the surgeon's takeover mid-throw, with h read at every physics step from the needle tip's trace.

The fast subset runs in CI; ``benchmarks/cbf_adversary.py`` runs 1,000+ episodes.
"""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from policy_builders import ExpertAsPolicy

import lerobot_suture
from lerobot_suture.experiments.attack_episodes import (
    CONDITIONS,
    AttackEpisode,
    EnvPath,
    conditions_for,
    lead_in,
    run_attack_episode,
    run_policy_attack,
)
from lerobot_suture.experiments.cbf_attacks import FAMILIES, random_rotation
from lerobot_suture.expert import ScriptedExpert
from lerobot_suture.runtime.rollout import SURGEON, rollout_episode
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.sim import controller
from lerobot_suture.sim.geometry import pose_vector, segment_distance
from lerobot_suture.sim.suture_env import SutureEnv

MARGIN = CBFConfig().margin


def assert_safe(episode: AttackEpisode) -> None:
    assert episode.active_steps > 0, f"{episode.family} seed {episode.seed}: the filter never came on"
    assert episode.violation_steps == 0, (
        f"{episode.family} seed {episode.seed}: {episode.violation_steps} physics steps with the held tip in "
        f"tissue outside the set (min h {episode.h_min}, {episode.depth_max * 1e3:.2f} mm deep)"
    )
    assert not episode.h_min < 0.0
    # The premise, measured: the tip stays within the margin of its commanded segment.
    assert max(episode.segment_deviations) < MARGIN


# Pure functions.


@st.composite
def ik_problems(draw):
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    jac_linear = rng.normal(scale=0.1, size=(3, 6))
    jac_angular = rng.normal(size=(3, 6))
    v = rng.normal(scale=0.05, size=3)
    w = rng.normal(scale=2.0, size=3)
    qdot_max = rng.uniform(0.2, 4.0, 6)
    # Some joints sit at a range stop: their box is one-sided.
    low = -qdot_max * rng.choice([0.0, 0.1, 1.0], 6)
    high = qdot_max * rng.choice([0.0, 0.1, 1.0], 6)
    return jac_linear, jac_angular, v, w, low, high


@settings(max_examples=300, derandomize=True, deadline=None)
@given(ik_problems())
def test_tip_first_ik_stays_in_bounds_and_moves_the_tip_along_its_command(problem):
    jac_linear, jac_angular, v, w, low, high = problem
    qdot, linear_scale, rotation_scale = controller.tip_first_velocity_ik(
        jac_linear, jac_angular, v, w, low, high
    )
    assert np.all(qdot >= low - 1e-12) and np.all(qdot <= high + 1e-12)
    assert 0.0 <= linear_scale <= 1.0 and 0.0 <= rotation_scale <= 1.0
    # The tip moves along its command (scaled down at worst), whatever the rotation asked for.
    tip = jac_linear @ qdot
    assert np.linalg.norm(tip - linear_scale * v) <= 0.02 * np.linalg.norm(v) + 1e-12


def test_tip_first_ik_tracks_both_when_free_and_drops_only_the_rotation_when_bound():
    rng = np.random.default_rng(0)
    jac_linear, jac_angular = rng.normal(scale=0.1, size=(3, 6)), rng.normal(size=(3, 6))
    v, w = np.array([0.01, -0.02, 0.005]), np.array([0.3, -0.2, 0.1])
    wide = np.full(6, 100.0)
    qdot, linear_scale, rotation_scale = controller.tip_first_velocity_ik(
        jac_linear, jac_angular, v, w, -wide, wide
    )
    assert linear_scale == rotation_scale == 1.0
    np.testing.assert_allclose(jac_linear @ qdot, v, rtol=1e-3, atol=1e-9)
    np.testing.assert_allclose(jac_angular @ qdot, w, rtol=1e-2, atol=1e-6)
    tight = np.abs(qdot) * 0.5 + 1e-9
    qdot, linear_scale, rotation_scale = controller.tip_first_velocity_ik(
        jac_linear, jac_angular, v, 100 * w, -tight, tight
    )
    assert rotation_scale < 1.0


def test_joint_velocity_bounds_slow_towards_stops_and_always_allow_stillness():
    q = np.array([0.0, 0.99, -1.2, 0.5])
    low, high = controller.joint_velocity_bounds(q, np.full(4, -1.0), np.full(4, 1.0), np.full(4, 2.0), 0.05)
    np.testing.assert_allclose(high, [2.0, 0.2, 2.0, 2.0])  # beyond a stop: back in, never further out
    np.testing.assert_allclose(low, [-2.0, -2.0, 0.0, -2.0])
    assert np.all(low <= 0.0) and np.all(high >= 0.0)


def test_segment_distance():
    start, end = np.zeros(3), np.array([1.0, 0.0, 0.0])
    points = np.array([[0.5, 0.2, 0.0], [-1.0, 0.0, 0.0], [2.0, 0.0, 0.3], [0.3, 0.0, 0.0]])
    np.testing.assert_allclose(segment_distance(points, start, end), [0.2, 1.0, math.hypot(1.0, 0.3), 0.0])
    np.testing.assert_allclose(segment_distance(points, start, start), np.linalg.norm(points, axis=1))


# Attack families in the simulator (the CI subset of benchmarks/cbf_adversary.py).


@pytest.mark.parametrize("family", FAMILIES)
def test_attack_family_never_takes_the_tip_out_of_the_set(family):
    for seed in (0, 1):
        assert_safe(run_attack_episode(family, seed, attack_steps=15))


def _conditions(path: str, within_bounds_only: bool = False) -> list:
    """The conditions of ``path`` as test parameters: still tissue by default, the rest with the slow set (which CI
    runs too)."""
    names = [c for c in conditions_for(path) if CONDITIONS[c].within_bounds or not within_bounds_only]
    slow = pytest.mark.slow
    return [c if c == "still" else pytest.param(c, marks=slow) for c in names]


@pytest.mark.parametrize("condition", _conditions("env", within_bounds_only=True))
@pytest.mark.parametrize("family", FAMILIES)
def test_every_family_in_every_condition_on_the_env_path(family, condition):
    """One episode per attack family and condition (the benchmark runs 1,000 a condition): tissue still,
    servoed, moved after insertion, breathing at the declared bound, and a running suture's throws."""
    seed = 3
    episode = run_attack_episode(family, seed, condition, attack_steps=15)
    assert episode.attack_steps > 0, f"{family} in {condition}: the attack never began"
    assert_safe(episode)


def test_the_harm_count_sees_a_second_entry_beside_the_wound_without_the_filter():
    """The measurement can fail: with the filter off, retracting, moving aside and pushing down enters the
    tissue beside the wound, and the count sees it at the physics rate."""
    episodes = [run_attack_episode("reenter", seed, cbf=CBFConfig(enabled=False)) for seed in range(4)]
    assert sum(e.violation_steps > 0 for e in episodes) >= 2, [e.depth_max for e in episodes]
    assert max(e.depth_max for e in episodes) > 0.002


def test_tissue_moving_beyond_the_declared_bounds_is_flagged_and_handed_over():
    """A glide of 30 mm over 1.5 s after insertion (66 mm/s^2 against a 20 mm/s^2 bound): the guard flags it,
    and a rollout hands control over at the flag."""
    path = EnvPath(CONDITIONS["beyond_bound_moved"])
    episode = AttackEpisode(family="expert", seed=0)
    assert lead_in(path, 0, 60, episode, 100) is None  # the expert's whole throw; the glide begins in it
    path.close()
    assert episode.moved_while_held and episode.motion_flagged
    assert episode.violation_steps == 0

    condition = CONDITIONS["beyond_bound_moved"]
    env = gym.make(
        lerobot_suture.ENV_ID,
        disable_env_checker=True,
        obs_type="state",
        cbf=CBFConfig(enabled=True),
        scenario=condition.scenario,
        scenario_magnitude=condition.scenario_magnitude,
    )
    log = rollout_episode(
        env, ExpertAsPolicy(env), seed=0, surgeon="expert"
    )  # no gate: only the premise hands over
    env.close()
    assert log.handover_cause == "tissue_motion" and log.steps[log.handover_step].controller == SURGEON
    assert log.steps[log.handover_step - 1].perturbed


@pytest.mark.parametrize("seed", [2, 5, 7])
def test_the_reported_rotation_attack_holds(seed):
    """The attack that once left the set: from the filter's first step, keep the jaw where it is and ask
    for a uniformly random jaw orientation every step for the rest of the episode. The rotation drove wrist
    joints into their range stops and the tip went where the filter had not allowed (h down to -0.48 in
    this pattern's episodes before the tip-first controller)."""
    path = EnvPath(CONDITIONS["still"])
    episode = AttackEpisode(family="rotation", seed=seed)
    rng = np.random.default_rng(seed)
    steps = lead_in(path, seed, 0, episode, 100)
    for _ in range(100 - steps):  # the rest of the episode's 100 control steps
        step = path.send(pose_vector(path.scene.unwrapped.jaw_pose()[0], random_rotation(rng), 1.0))
        episode.attack_steps += 1
        episode.record(path, step)
        if step.over:
            break
    path.close()
    assert episode.attack_steps > 5
    assert_safe(episode)


# Property tests: any state (seed, depth into the throw), any action sequence from the action space.

_SPACE = SutureEnv(obs_type="state").action_space


@st.composite
def action_sequences(draw):
    n = draw(st.integers(1, 10))
    actions = []
    for _ in range(n):
        raw = draw(st.lists(st.floats(0.0, 1.0), min_size=10, max_size=10))
        action = _SPACE.low + np.asarray(raw) * (_SPACE.high - _SPACE.low)
        if np.linalg.norm(np.cross(action[3:6], action[6:9])) < 1e-3:  # the env rejects parallel columns
            action[3:9] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
        actions.append(action.astype(np.float32))
    return actions


@settings(max_examples=12, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), delay=st.integers(0, 12), actions=action_sequences())
def test_any_action_sequence_keeps_h_nonnegative_at_every_physics_step(seed, delay, actions):
    path = EnvPath(CONDITIONS["still"])
    episode = AttackEpisode(family="property", seed=seed)
    if lead_in(path, seed, delay, episode, 100) is not None:
        for action in actions:
            step = path.send(action)
            episode.record(path, step)
            if step.over:
                break
    path.close()
    assert episode.violation_steps == 0, (episode.h_min, seed, delay)
    if episode.segment_deviations:
        assert max(episode.segment_deviations) < MARGIN


# The surgeon's takeover, and a policy off distribution.


class _GateThatReleasesMidThrow:
    """Stands in for a policy and its gate: it acts as the expert until the needle has been in tissue for
    ``depth`` steps, then asks for random jaw rotations (off distribution), and its gate flags O.O.D. and
    releases control ``release_after`` steps into that, mid-insertion."""

    def __init__(self, env: gym.Env, depth: int = 5, release_after: int = 1, seed: int = 0):
        self.env, self.depth, self.release_after = env, depth, release_after
        self.rng = np.random.default_rng(seed)
        self.policy = self
        self.reset()

    def reset(self, seeds=None) -> None:
        self.expert, self.in_tissue_steps, self.off_steps, self.released = ScriptedExpert(), 0, 0, False
        self.expert.reset(self.env)

    def act_batch(self, observations, tasks=None):
        u = self.env.unwrapped
        self.in_tissue_steps += int(u.needle_in_tissue)
        if self.in_tissue_steps <= self.depth:
            return [self.expert.act(self.env)]
        self.off_steps += 1
        self.released = self.off_steps > self.release_after
        return [pose_vector(u.jaw_pose()[0], random_rotation(self.rng), 1.0).astype(np.float32)]

    def ood_status(self, i):
        return {
            "score": float(self.off_steps),
            "threshold": float(self.release_after),
            "decision": self.released,
            "released": self.released,
            "new_prediction": True,
        }


@pytest.mark.parametrize("seed", [0, 3])
def test_handover_mid_insertion_keeps_h_nonnegative_and_filters_the_surgeon(seed):
    env = gym.make(
        lerobot_suture.ENV_ID,
        disable_env_checker=True,
        obs_type="state",
        cbf=CBFConfig(enabled=True),
        record_tip_trace=True,
    )
    log = rollout_episode(env, _GateThatReleasesMidThrow(env, seed=seed), seed=seed, surgeon="expert")
    env.close()
    handover = log.handover_step
    assert handover is not None and log.steps[handover - 1].needle_in_tissue  # released mid-insertion
    assert all(step.cbf_active for step in log.steps[handover - 3 : handover + 1])  # the filter spans it
    surgeon_steps = [step for step in log.steps if step.controller == SURGEON]
    assert surgeon_steps and any(step.cbf_active for step in surgeon_steps)  # the surgeon is filtered
    assert log.h_min_physics >= 0.0
    assert log.success  # the surgeon, filtered, finishes the throw


def test_off_distribution_policy_taking_over_a_throw_stays_in_the_set(tiny_policy_dir):
    """An untrained tiny ensemble (the expert's statistics, so its actions have the right units) in the
    camera_moved scenario takes over a begun throw; its gate is not consulted."""
    from lerobot_suture.runtime.policy import GateMode, PolicyRunner

    runner = PolicyRunner.from_pretrained(tiny_policy_dir, GateMode.REPORT)
    assert_safe(run_policy_attack(runner, seed=0, attack_steps=6, max_start_delay=0))
