"""Tests of the ellipsoid CBF: the math (property tests), the discrete-time filter, the config, the
offline replay figure, and the env wrapper against a kinematic stand-in of SutureEnv."""

from __future__ import annotations

import math

import gymnasium as gym
import matplotlib.image
import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from lerobot_suture.safety.cbf import (
    ellipsoid_grad_h,
    ellipsoid_h,
    filter_velocity,
    filter_velocity_discrete,
    inward_normal,
    margin_level,
    suture_ellipsoid_frame,
)
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.safety.cbf_replay import replay_and_plot, replay_cbf
from lerobot_suture.safety.cbf_wrapper import PHASE_ACTIVE, PHASE_DONE, PHASE_IDLE, CBFActionWrapper
from lerobot_suture.sim.tasks import TASKS

N_STATES = 10_000
DT = 0.1


def random_problem(n: int, seed: int, inside: bool = True):
    """Random ellipsoids (centre, axes, rotation), tip states and nominal velocities, (n, ...)."""
    rng = np.random.default_rng(seed)
    center = rng.normal(scale=0.05, size=(n, 3))
    axes = rng.uniform(0.003, 0.03, size=(n, 3))
    rotation = Rotation.random(n, random_state=rng).as_matrix()
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    radius = rng.uniform(0.0, 1.0, n) ** (1 / 3)
    radius[: n // 10] = rng.uniform(0.99, 1.0, n // 10)  # near the boundary
    radius[n // 10 : n // 5] = rng.uniform(0.0, 0.01, n // 10)  # near the centre
    if not inside:
        radius = rng.uniform(0.0, 1.5, n)
    local = direction * radius[:, None] * axes
    x = center + np.einsum("nij,nj->ni", rotation, local)
    speed = 10.0 ** rng.uniform(-4, 0, n)  # 0.1 mm/s .. 1 m/s
    v_dir = rng.normal(size=(n, 3))
    v_nominal = v_dir / np.linalg.norm(v_dir, axis=1, keepdims=True) * speed[:, None]
    alpha = float(rng.uniform(0.5, 20.0))
    return x, v_nominal, center, axes, rotation, alpha


def reference_h_and_normal(x, center, axes, rotation):
    """Independent plain-numpy h and unit inward normal, (n,) and (n, 3)."""
    e = np.einsum("nji,nj->ni", rotation, x - center)
    h = 1.0 - np.sum(e**2 / axes**2, axis=1)
    grad = -2.0 * np.einsum("nij,nj->ni", rotation, e / axes**2)
    return h, grad / np.linalg.norm(grad, axis=1, keepdims=True)


# The barrier.


def test_h_and_normal_match_plain_numpy():
    x, _, center, axes, rotation, _ = random_problem(N_STATES, seed=0, inside=False)
    h_ref, n_ref = reference_h_and_normal(x, center, axes, rotation)
    np.testing.assert_allclose(ellipsoid_h(x, center, axes, rotation), h_ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(inward_normal(x, center, axes, rotation), n_ref, rtol=1e-9, atol=1e-12)


def test_gradient_matches_finite_differences():
    x, _, center, axes, rotation, _ = random_problem(200, seed=1)
    eps = 1e-7
    numeric = np.stack(
        [
            (
                ellipsoid_h(x + eps * e, center, axes, rotation)
                - ellipsoid_h(x - eps * e, center, axes, rotation)
            )
            / (2 * eps)
            for e in np.eye(3)
        ],
        axis=1,
    )
    analytic = ellipsoid_grad_h(x, center, axes, rotation)
    np.testing.assert_allclose(analytic, numeric, rtol=1e-5, atol=1e-3)


def test_h_values_at_centre_surface_and_outside():
    axes = np.array([0.016, 0.008, 0.010])
    assert ellipsoid_h(np.zeros(3), np.zeros(3), axes) == 1.0
    for i in range(3):
        on_surface = np.zeros(3)
        on_surface[i] = axes[i]
        assert ellipsoid_h(on_surface, np.zeros(3), axes) == pytest.approx(0.0, abs=1e-15)
        assert ellipsoid_h(2 * on_surface, np.zeros(3), axes) == pytest.approx(-3.0)


@pytest.mark.parametrize(
    "axes",
    [
        [0.01, 0.0, 0.01],
        [0.01, -0.002, 0.01],
        [np.nan, 0.01, 0.01],
        [0.01, np.nan, 0.01],
        [0.01, 0.01, np.inf],
    ],
)
def test_invalid_axes_raise(axes):
    x = np.zeros(3)
    for call in (
        lambda: ellipsoid_h(x, x, axes),
        lambda: inward_normal(x, x, axes),
        lambda: filter_velocity(x, x, x, axes, 1.0),
        lambda: filter_velocity_discrete(x, x, x, axes, 1.0, DT),
        lambda: filter_velocity(np.zeros((4, 3)), np.zeros((4, 3)), x, [axes] * 4, 1.0),
    ):
        with pytest.raises(ValueError, match="`axes` must be > 0"):
            call()


def test_invalid_scalars_and_shapes_raise():
    x, axes = np.zeros(3), np.full(3, 0.01)
    with pytest.raises(ValueError, match="`alpha` must be > 0"):
        filter_velocity(x, x, x, axes, -1.0)
    with pytest.raises(ValueError, match="`dt` must be > 0"):
        filter_velocity_discrete(x, x, x, axes, 1.0, 0.0)
    with pytest.raises(ValueError, match="`margin` must be in"):
        filter_velocity_discrete(x, x, x, axes, 1.0, DT, margin=0.01)
    with pytest.raises(ValueError, match="`margin` must be in"):
        filter_velocity_discrete(x, x, x, axes, 1.0, DT, margin=-0.001)
    with pytest.raises(ValueError, match="`x` must have shape"):
        ellipsoid_h(np.zeros(2), x, axes)
    with pytest.raises(ValueError, match="`rotation` must have shape"):
        ellipsoid_h(x, x, axes, np.eye(2))


def test_centre_has_zero_normal_and_passes_nominal_velocity():
    center = np.array([0.1, -0.2, 0.05])
    axes = np.array([0.016, 0.008, 0.010])
    rotation = Rotation.from_euler("xyz", [0.3, -0.5, 1.0]).as_matrix()
    v = np.array([3.0, -2.0, 1.0])  # far beyond anything alpha h allows elsewhere
    np.testing.assert_array_equal(inward_normal(center, center, axes, rotation), np.zeros(3))
    np.testing.assert_array_equal(ellipsoid_grad_h(center, center, axes, rotation), np.zeros(3))
    result = filter_velocity(center, v, center, axes, 5.0, rotation)
    np.testing.assert_array_equal(result.v_safe, v)
    assert result.h == 1.0 and not result.intervened
    # The discrete filter has no normal there either, but still limits the step to stay inside.
    result = filter_velocity_discrete(center, v, center, axes, 5.0, DT, 0.001, rotation)
    assert result.correction == 0.0 and result.intervened
    end = center + result.v_safe * DT
    assert ellipsoid_h(end, center, axes, rotation) >= margin_level(0.001, axes) - 1e-12
    # Batched, the centre rows behave the same as single calls.
    xs = np.stack([center, center + 1e-3])
    vs = np.stack([v, v])
    batch = filter_velocity(xs, vs, center, axes, 5.0, rotation)
    np.testing.assert_array_equal(batch.v_safe[0], v)


# The paper's continuous-time closed form.


def test_closed_form_satisfies_the_cbf_condition():
    x, v, center, axes, rotation, alpha = random_problem(N_STATES, seed=2)
    result = filter_velocity(x, v, center, axes, alpha, rotation)
    h, n = reference_h_and_normal(x, center, axes, rotation)
    assert np.all(np.sum(n * result.v_safe, axis=1) >= -alpha * h - 1e-9)
    np.testing.assert_allclose(result.h, h, atol=1e-12)
    assert np.all(result.correction >= 0.0) and np.all(result.step_scale == 1.0)
    # The correction is along the normal only: the tangential part of v is kept.
    tangential = (result.v_safe - v) - np.sum((result.v_safe - v) * n, axis=1, keepdims=True) * n
    assert np.abs(tangential).max() < 1e-12


def test_closed_form_is_minimal_intervention():
    x, v, center, axes, rotation, alpha = random_problem(N_STATES, seed=3)
    v = v * 30.0  # up to 30 m/s: alpha h is a speed of order alpha m/s deep inside
    h, n = reference_h_and_normal(x, center, axes, rotation)
    satisfied = np.sum(n * v, axis=1) >= -alpha * h + 1e-12
    assert 500 < satisfied.sum() < N_STATES - 500  # both cases are exercised
    result = filter_velocity(x, v, center, axes, alpha, rotation)
    np.testing.assert_array_equal(result.v_safe[satisfied], v[satisfied])
    assert not result.intervened[satisfied].any()
    assert result.intervened[~satisfied].all()


def test_closed_form_matches_a_qp_solved_by_scipy():
    x, v, center, axes, rotation, alpha = random_problem(300, seed=4)
    result = filter_velocity(x, v, center, axes, alpha, rotation)
    _, n = reference_h_and_normal(x, center, axes, rotation)
    for i in range(len(x)):
        scale = max(np.linalg.norm(v[i]), 1e-3)  # solve in units of |v_n| for conditioning
        target, normal, rhs = v[i] / scale, n[i], -alpha * result.h[i] / scale
        solution = minimize(
            lambda u, t=target: np.sum((u - t) ** 2),
            x0=np.zeros(3),
            jac=lambda u, t=target: 2 * (u - t),
            constraints=[
                {"type": "ineq", "fun": lambda u, m=normal, r=rhs: m @ u - r, "jac": lambda u, m=normal: m}
            ],
            method="SLSQP",
            options={"ftol": 1e-14, "maxiter": 200},
        )
        assert solution.success
        np.testing.assert_allclose(result.v_safe[i], solution.x * scale, atol=1e-6 * scale)


def test_batch_and_single_give_identical_results():
    x, v, center, axes, rotation, alpha = random_problem(300, seed=5, inside=False)
    shared_center, shared_axes, shared_rotation = center[0], axes[0], rotation[0]
    for rot in (None, shared_rotation):
        batch = filter_velocity(x, v, shared_center, shared_axes, alpha, rot)
        batch_d = filter_velocity_discrete(x, v, shared_center, shared_axes, alpha, DT, 0.001, rot)
        for i in range(len(x)):
            single = filter_velocity(x[i], v[i], shared_center, shared_axes, alpha, rot)
            single_d = filter_velocity_discrete(x[i], v[i], shared_center, shared_axes, alpha, DT, 0.001, rot)
            for got, want in ((single, batch), (single_d, batch_d)):
                np.testing.assert_array_equal(got.v_safe, want.v_safe[i])
                assert got.h == want.h[i] and got.intervened == want.intervened[i]
                assert got.correction == want.correction[i] and got.step_scale == want.step_scale[i]
    # Per-row ellipsoids (batched centre, axes, rotation) equal row-by-row calls.
    batch = filter_velocity_discrete(x, v, center, axes, alpha, DT, 0.0005, rotation)
    for i in range(0, len(x), 7):
        single = filter_velocity_discrete(x[i], v[i], center[i], axes[i], alpha, DT, 0.0005, rotation[i])
        np.testing.assert_array_equal(single.v_safe, batch.v_safe[i])


# The discrete-time filter.


def segment_h_min(x, v, center, axes, rotation, dt=DT, n_sub=50):
    """Smallest h over the physics sub-steps of holding v for dt from x, (n,)."""
    fractions = np.linspace(0.0, 1.0, n_sub + 1)[:, None, None]
    points = x[None] + fractions * (v * dt)[None]  # (n_sub + 1, n, 3)
    return ellipsoid_h(points, center[None], axes[None], rotation[None]).min(axis=0)


def test_discrete_filter_keeps_h_nonnegative_over_the_whole_step():
    x, v, center, axes, rotation, alpha = random_problem(N_STATES, seed=6)
    v = v * 10.0  # up to 10 m/s: steps far larger than the ellipsoid
    margin = 0.1 * axes.min(axis=1).min()
    result = filter_velocity_discrete(x, v, center, axes, alpha, DT, margin, rotation)
    h_m = margin_level(margin, axes)
    h_tight = result.h - h_m
    end_tight = ellipsoid_h(x + result.v_safe * DT, center, axes, rotation) - h_m
    gamma = min(alpha * DT, 1.0)
    started_in = h_tight >= 0
    # The discrete-time CBF condition, where the tip starts inside the tightened set...
    assert np.all(end_tight[started_in] >= (1 - gamma) * h_tight[started_in] - 1e-12)
    # ...so h >= h_m >= 0 at every physics sub-step of the control step (h is concave).
    assert np.all(
        segment_h_min(x, result.v_safe, center, axes, rotation)[started_in] >= h_m[started_in] - 1e-12
    )
    # Elsewhere (margin band) h never decreases over the step.
    assert np.all(end_tight[~started_in] >= h_tight[~started_in] - 1e-12)
    assert np.all((result.step_scale >= 0) & (result.step_scale <= 1))


def test_discrete_filter_without_margin_keeps_h_nonnegative():
    x, v, center, axes, rotation, alpha = random_problem(N_STATES, seed=7)
    result = filter_velocity_discrete(x, v, center, axes, alpha, DT, 0.0, rotation)
    assert np.all(segment_h_min(x, result.v_safe, center, axes, rotation) >= -1e-12)


def test_discrete_filter_recovers_from_outside():
    x, v, center, axes, rotation, alpha = random_problem(N_STATES, seed=8, inside=False)
    result = filter_velocity_discrete(x, v, center, axes, alpha, DT, 0.0, rotation)
    end = ellipsoid_h(x + result.v_safe * DT, center, axes, rotation)
    outside = result.h < 0
    assert outside.sum() > 1000
    assert np.all(end[outside] >= result.h[outside] - 1e-12)  # h never decreases over the step
    assert np.all(
        segment_h_min(x, result.v_safe, center, axes, rotation)[outside] >= result.h[outside] - 1e-12
    )


def test_discrete_filter_is_minimal_intervention():
    x, v, center, axes, rotation, alpha = random_problem(N_STATES, seed=9)
    margin = 0.0005
    h_m = margin_level(margin, axes)
    h_tight = ellipsoid_h(x, center, axes, rotation) - h_m
    end_tight = ellipsoid_h(x + v * DT, center, axes, rotation) - h_m
    satisfied = end_tight >= (1 - min(alpha * DT, 1.0)) * h_tight + 1e-9
    assert 0.05 < satisfied.mean() < 0.99
    result = filter_velocity_discrete(x, v, center, axes, alpha, DT, margin, rotation)
    np.testing.assert_array_equal(result.v_safe[satisfied], v[satisfied])
    assert not result.intervened[satisfied].any()


def test_continuous_closed_form_alone_leaves_the_set_in_discrete_time():
    """The discrete-time gap: a tangential step on the boundary passes the paper's filter and exits."""
    axes = np.array([0.016, 0.008, 0.010])
    x = np.array([0.0, 0.0, 0.0099])  # just under the top
    v = np.array([0.05, 0.0, 0.0])  # tangential, 5 mm per step
    result = filter_velocity(x, v, np.zeros(3), axes, 5.0)
    assert not result.intervened
    assert ellipsoid_h(x + result.v_safe * DT, np.zeros(3), axes) < 0
    result = filter_velocity_discrete(x, v, np.zeros(3), axes, 5.0, DT, 0.0)
    assert result.intervened and ellipsoid_h(x + result.v_safe * DT, np.zeros(3), axes) >= -1e-15


# Configuration and the suture geometry.


def test_config_validation_messages():
    assert CBFConfig().enabled is False
    with pytest.raises(ValueError, match=r"`alpha` must be > 0. Got -1."):
        CBFConfig(alpha=-1)
    with pytest.raises(ValueError, match=r"`semi_axis_lateral` must be > 0. Got 0.0."):
        CBFConfig(semi_axis_lateral=0.0)
    with pytest.raises(ValueError, match=r"`margin` must be in \[0, 0.008\)"):
        CBFConfig(margin=0.01)
    with pytest.raises(ValueError, match="`alpha` must be a finite number"):
        CBFConfig(alpha=math.nan)
    with pytest.raises(ValueError, match="`enabled` must be a bool"):
        CBFConfig(enabled="yes")


def nominal_throw(n_approach=10, n_arc=30, radius=0.010, half_chord=0.009, tilt=math.pi / 6, protrude=0.005):
    """Needle-tip path of a nominal throw in the ellipsoid frame (m): approach from above the entry
    point, the arc under the surface (needle plane tilted from vertical), then the protrusion."""
    height = math.sqrt(radius**2 - half_chord**2)
    theta = np.linspace(
        -math.asin(half_chord / radius), math.asin(half_chord / radius) + protrude / radius, n_arc
    )
    w = height - radius * np.cos(theta)  # below (-) / above (+) the surface, in the needle plane
    arc = np.stack([radius * np.sin(theta), w * math.sin(tilt), w * math.cos(tilt)], axis=1)
    approach = arc[0] + np.linspace(1, 0, n_approach, endpoint=False)[:, None] * np.array([0.0, 0.0, 0.012])
    return np.concatenate([approach, arc])


def sideways_pull(k_in=20, pull=0.02, n_pull=15):
    """A nominal throw until step ``k_in`` (tip in tissue), then a 2 cm pull along the lateral axis."""
    path = nominal_throw()[: k_in + 1]
    pulls = path[-1] + np.linspace(0, 1, n_pull + 1)[1:, None] * np.array([0.0, pull, 0.0])
    return np.concatenate([path, pulls, np.repeat(pulls[-1:], 5, axis=0)])


def test_default_ellipsoid_contains_a_nominal_throw_with_margin():
    config = CBFConfig()
    throw = nominal_throw()[10:]  # from the entry point on
    h = ellipsoid_h(throw, np.zeros(3), config.semi_axes)
    assert h.min() > config.margin_level + 0.05


def test_suture_ellipsoid_frame():
    entry, exit_ = np.array([0.1, 0.2, 0.05]), np.array([0.1, 0.218, 0.052])
    normal = np.array([0.0, 0.0, 2.0])
    center, rotation = suture_ellipsoid_frame(entry, exit_, normal)
    np.testing.assert_allclose(center, (entry + exit_) / 2)
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    np.testing.assert_allclose(rotation[:, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(rotation[:, 2], [0, 0, 1], atol=1e-12)
    axes = CBFConfig().semi_axes
    assert (
        ellipsoid_h(entry, center, axes, rotation) > 0.5 and ellipsoid_h(exit_, center, axes, rotation) > 0.5
    )
    with pytest.raises(ValueError, match="must be apart"):
        suture_ellipsoid_frame(entry, entry + normal, normal)


# Offline replay (the paper's experiment 4).


def test_replay_blocks_a_sideways_pull(tmp_path):
    axes = CBFConfig().semi_axes
    reference = sideways_pull()
    metrics = replay_and_plot(reference, DT, np.zeros(3), axes, None, 5.0, tmp_path / "cbf.png")
    assert metrics["left_set_reference"] is True
    assert metrics["left_set_safe"] is False and metrics["h_min_safe"] >= 0.0
    assert metrics["steps_intervened"] > 0
    image = matplotlib.image.imread(tmp_path / "cbf.png")
    assert image.shape[0] > 300 and image.shape[1] > 900
    assert image[..., :3].std() > 0.05  # not blank


def test_replay_leaves_a_safe_trajectory_alone():
    rotation = Rotation.from_euler("z", 0.7).as_matrix()
    center = np.array([0.01, 0.02, 0.03])
    reference = center + nominal_throw() @ rotation.T
    replay = replay_cbf(reference, DT, center, CBFConfig().semi_axes, rotation, 5.0, tracking_rate=None)
    assert replay.active[10:].all() and not replay.intervened.any()
    np.testing.assert_allclose(replay.actual[:: replay.substeps], reference, atol=1e-12)


def test_replay_with_the_paper_filter_shows_the_gap():
    """The paper's closed form alone, held for 0.1 s steps, lets the pulled tip leave the set."""
    axes = CBFConfig().semi_axes
    with np.errstate(all="ignore"):  # once outside, its inward push of alpha |h| m/s overshoots and diverges
        replay = replay_cbf(sideways_pull(), DT, np.zeros(3), axes, None, 5.0, discrete=False)
    k0 = replay.activation_index
    assert np.any(replay.h_actual[k0 * replay.substeps :] < 0.0)


# The env wrapper, against a kinematic stand-in that honours SutureEnv's contract.


class KinematicSutureEnv(gym.Env):
    """The tip moves with the (filtered) Cartesian velocity; the action is the tip's target position."""

    metadata = {"render_modes": []}
    control_dt, physics_dt = 0.1, 0.002
    task_spec = TASKS["insertion"]
    throw_index = 0

    def __init__(self):
        self.observation_space = gym.spaces.Box(-1, 1, (3,), np.float64)
        self.action_space = gym.spaces.Box(-1, 1, (4,), np.float64)  # target tip (3), jaw closed (1)
        self.tip_velocity_filter = None
        rotation = Rotation.from_euler("z", 0.4).as_matrix()
        self.phantom_rotation = rotation
        self.phantom_position = np.zeros(3)
        self.entry_point = np.array([0.0, 0.0, 0.0]) + rotation @ [-0.009, 0.0, 0.0]
        self.exit_point = np.array([0.0, 0.0, 0.0]) + rotation @ [0.009, 0.0, 0.0]

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.needle_tip_pos = self.entry_point + np.array([0.0, 0.0, 0.02])
        self.needle_grasped, self.needle_in_tissue = True, False
        return self.needle_tip_pos.copy(), {"needle_tip_pos": self.needle_tip_pos.copy()}

    def step(self, action):
        v = (np.asarray(action[:3]) - self.needle_tip_pos) / self.control_dt
        if self.tip_velocity_filter is not None:
            v = self.tip_velocity_filter(self.needle_tip_pos.copy(), v)
        n_sub = round(self.control_dt / self.physics_dt)
        trace = self.needle_tip_pos + np.outer(np.arange(1, n_sub + 1) * self.physics_dt, v)
        self.needle_tip_pos = trace[-1].copy()
        self.needle_grasped = bool(action[3] > 0.5)
        self.needle_in_tissue = bool((self.phantom_rotation.T @ self.needle_tip_pos)[2] < 0.0)
        info = {
            "needle_tip_pos": self.needle_tip_pos.copy(),
            "needle_in_tissue": self.needle_in_tissue,
            "needle_grasped": self.needle_grasped,
            "needle_tip_trace": trace,
            "needle_tip_trace_phantom": (trace - self.phantom_position) @ self.phantom_rotation,
        }
        return self.needle_tip_pos.copy(), 0.0, False, False, info


def run_pull(enabled: bool, release: bool = False):
    env = CBFActionWrapper(KinematicSutureEnv(), CBFConfig(enabled=enabled))
    _, info = env.reset(seed=0)
    assert set(info) >= {"cbf_active", "h", "v_nominal", "v_safe", "cbf_intervened"}
    base = env.unwrapped
    lateral = base.phantom_rotation[:, 1]
    targets = [
        base.entry_point + [0, 0, 0.01],
        base.entry_point,
        base.entry_point - 0.004 * base.phantom_rotation[:, 2],
    ]
    targets += [targets[-1] + 0.02 * lateral] * 10
    infos, phases = [], []
    for k, target in enumerate(targets):
        *_, info = env.step(np.append(target, 0.0 if release and k >= 3 else 1.0))
        infos.append(info)
        phases.append(env.phase)
    env.close()
    assert base.tip_velocity_filter is None
    return env, infos, phases


def trace_h_min(env, infos):
    return min(env.h_min(i) for i in infos if i["cbf_active"])


def test_wrapper_keeps_the_tip_in_the_set_at_every_physics_step():
    env_off, infos_off, phases = run_pull(enabled=False)
    assert phases[0] == PHASE_IDLE and PHASE_ACTIVE in phases
    assert trace_h_min(env_off, infos_off) < 0.0  # the pull leaves the set without the filter
    assert not any(i["cbf_intervened"] for i in infos_off)
    env_on, infos_on, phases = run_pull(enabled=True)
    assert phases[-1] == PHASE_ACTIVE
    assert trace_h_min(env_on, infos_on) >= 0.0
    assert any(i["cbf_intervened"] for i in infos_on)
    last = infos_on[-1]
    assert last["h"] >= 0.0 and last["v_nominal"].shape == (3,) and np.isfinite(last["v_safe"]).all()


def test_wrapper_releases_after_the_needle_is_let_go():
    _, infos, phases = run_pull(enabled=True, release=True)
    assert phases[2] == PHASE_ACTIVE and phases[-1] == PHASE_DONE
    assert not infos[-1]["cbf_active"]
