"""The CBF live in the loop of SutureEnv: an adversary pulls the needle sideways out of the wound.

The adversary runs the scripted expert until the needle has been in tissue for a few steps, then
commands the jaw 2 cm along the phantom's lateral axis (orientation kept, jaw closed) and holds that
target. Safety is checked at every physics step from ``info["needle_tip_trace"]``.
"""

from __future__ import annotations

import numpy as np
import pytest

from lerobot_suture.experiments.sideways_pull import CBFEpisode, run_cbf_episode
from lerobot_suture.expert import ScriptedExpert
from lerobot_suture.safety.cbf import margin_level
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.safety.cbf_wrapper import PHASE_ACTIVE, CBFActionWrapper
from lerobot_suture.safety.tip_guard import TipGuard
from lerobot_suture.sim.suture_env import SutureEnv

PULL_DISTANCE = 0.02  # m, along the phantom's lateral axis
STEPS_IN_TISSUE_BEFORE_PULL = 3
PULL_STEPS = 20
MAX_STEPS = 100
FAST_SEEDS = range(5)
SLOW_SEEDS = range(5, 35)


def run_episode(seed: int, enabled: bool, adversarial: bool) -> CBFEpisode:
    return run_cbf_episode(
        seed,
        CBFConfig(enabled=enabled),
        adversarial,
        PULL_DISTANCE,
        STEPS_IN_TISSUE_BEFORE_PULL,
        PULL_STEPS,
        MAX_STEPS,
    )


def check_sideways_pull(seeds) -> None:
    strain_off, strain_on = [], []
    for seed in seeds:
        off = run_episode(seed, enabled=False, adversarial=True)
        on = run_episode(seed, enabled=True, adversarial=True)
        assert off.h_min_pull < 0.0, f"seed {seed}: the pull should leave the safe set without the filter"
        assert on.phases[-1] == PHASE_ACTIVE, (
            f"seed {seed}: the filter must stay on while the needle is held in tissue"
        )
        assert on.h_min_active >= 0.0, (
            f"seed {seed}: h = {on.h_min_active} < 0 at a physics step with the filter on"
        )
        assert on.interventions > 0
        strain_off.append(off.tissue_strain)
        strain_on.append(on.tissue_strain)
    strain_off, strain_on = np.array(strain_off), np.array(strain_on)
    assert np.all(strain_on < strain_off), (strain_on, strain_off)
    assert strain_on.mean() < 0.5 * strain_off.mean()


def test_sideways_pull_leaves_the_set_without_the_filter_and_never_with_it():
    check_sideways_pull(FAST_SEEDS)


@pytest.mark.slow
def test_sideways_pull_many_seeds():
    check_sideways_pull(SLOW_SEEDS)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_filter_leaves_the_expert_throw_alone(seed):
    off = run_episode(seed, enabled=False, adversarial=False)
    on = run_episode(seed, enabled=True, adversarial=False)
    assert off.success and on.success
    assert PHASE_ACTIVE in on.phases and on.interventions == 0
    assert on.h_min_active >= 0.0
    assert on.tissue_strain == off.tissue_strain


def free_pull(seed: int, enabled: bool, direction: np.ndarray) -> tuple[float, float, float]:
    """Pull 3 cm in ``direction`` (ellipsoid frame) as soon as the throw has begun, before the needle touches
    tissue (no tissue resistance: the tip goes where the filter lets it). Returns the smallest barrier of the
    safe set over the physics steps, and the ellipsoid's h and the tip's height above the surface (m) at the
    end."""
    env = CBFActionWrapper(SutureEnv(obs_type="state", record_tip_trace=True), CBFConfig(enabled=enabled))
    env.reset(seed=seed)
    expert = ScriptedExpert()
    expert.reset(env)
    pull_action, h_min, info = None, np.inf, {}
    for _ in range(60):
        if pull_action is None and env.phase == PHASE_ACTIVE:
            _, _, rotation = env.safe_set()
            pull_action = expert.act(env).copy()
            pull_action[:3] += 0.03 * rotation @ direction
        _, _, _, _, info = env.step(expert.act(env) if pull_action is None else pull_action)
        if pull_action is not None:
            h_min = min(h_min, env.h_min(info))
    wound = env.wound()
    height = float((info["needle_tip_pos"] - wound.entry_point) @ wound.surface_normal)
    env.close()
    return h_min, info["h"], height


@pytest.mark.parametrize("direction", [(0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (-0.6, -0.8, 0.0)])
def test_a_free_pull_above_the_tissue_leaves_the_wound_freely(direction):
    """Above the tissue the tip may go anywhere: the pull in the surface's plane takes it out of the
    ellipsoid, with the filter on as without it, and never into the tissue."""
    for seed in (0, 1):
        h_min_on, h_end_on, height = free_pull(seed, enabled=True, direction=np.array(direction))
        assert h_end_on < 0.0 and height > 0.0
        assert h_min_on >= 0.0


@pytest.mark.parametrize("direction", [(0.0, 0.6, -0.8), (0.8, 0.0, -0.6), (-0.6, -0.48, -0.64)])
def test_a_free_pull_into_the_tissue_beside_the_wound_stops_at_the_tightened_union(direction):
    config = CBFConfig()
    margin = TipGuard(config).margin(0.1)  # the tracking margin and the tissue's
    level = margin_level(margin, config.semi_axes)
    for seed in (0, 1):
        h_min_off, _, _ = free_pull(seed, enabled=False, direction=np.array(direction))
        h_min_on, h_end_on, height = free_pull(seed, enabled=True, direction=np.array(direction))
        assert h_min_off < 0.0
        # The tip slides to the boundary of the tightened union, no further at any physics step: onto the
        # surface raised by the margin beside the wound, or into the tissue up to the tightened ellipsoid.
        assert h_min_on >= 0.0
        on_surface = 0.8 * margin < height < 1.5 * margin and h_end_on < level
        in_wound = abs(h_end_on - level) < 0.02
        assert on_surface or in_wound, (height, h_end_on)
