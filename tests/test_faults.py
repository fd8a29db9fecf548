"""Fault injection on the robot path: validation and each fault's semantics on synthetic observations."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from lerobot_robot_suture import POSE_FEATURES
from lerobot_robot_suture.faults import POSE_KEYS, FaultConfig, FaultInjector

IDENTITY_POSE = np.array([0.0, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 1.0])


def frame(step: int) -> np.ndarray:
    """A (4, 4, 3) uint8 frame that tells its step."""
    return np.full((4, 4, 3), step % 256, dtype=np.uint8)


def observation(step: int) -> dict:
    obs = {key: float(step) for key in POSE_KEYS}
    obs["endoscope"] = frame(step)
    return obs


def run(config: FaultConfig, steps: int = 12, scene_seed: int = 0) -> list[dict]:
    injector = FaultInjector(config)
    injector.reset(scene_seed)
    return [injector.observe(observation(k)) for k in range(steps)]


def frame_steps(outputs: list[dict]) -> list[int]:
    return [int(o["endoscope"][0, 0, 0]) for o in outputs]


def test_pose_keys_are_the_robots():
    assert POSE_KEYS == tuple(POSE_FEATURES)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("frozen_camera_step", -1, "`frozen_camera_step` must be None or >= 0. Got -1."),
        ("dropped_frame_rate", 1.0, "`dropped_frame_rate` must be in [0, 1). Got 1.0."),
        ("dropped_frame_rate", -0.1, "`dropped_frame_rate` must be in [0, 1). Got -0.1."),
        ("observation_latency", 11, "`observation_latency` must be in [0, 10]. Got 11."),
        ("observation_latency", -1, "`observation_latency` must be in [0, 10]. Got -1."),
        ("command_latency", 11, "`command_latency` must be in [0, 10]. Got 11."),
        ("arm_lag", 1.0, "`arm_lag` must be in [0, 1). Got 1.0."),
        ("arm_lag", -0.5, "`arm_lag` must be in [0, 1). Got -0.5."),
        ("seed", -3, "`seed` must be >= 0. Got -3."),
    ],
)
def test_config_rejects_out_of_range(field, value, message):
    with pytest.raises(ValueError) as error:
        FaultConfig(**{field: value})
    assert str(error.value) == message


def test_any_is_true_exactly_when_a_fault_is_on():
    assert not FaultConfig().any
    assert not FaultConfig(seed=5).any
    for fault in (
        {"frozen_camera_step": 0},
        {"dropped_frame_rate": 0.1},
        {"observation_latency": 1},
        {"command_latency": 1},
        {"arm_lag": 0.2},
    ):
        assert FaultConfig(**fault).any, fault


def test_no_fault_passes_observations_and_commands_through():
    injector = FaultInjector(FaultConfig())
    obs = observation(3)
    out = injector.observe(obs)
    assert out is not obs and out.keys() == obs.keys()
    assert all(out[k] == obs[k] for k in POSE_KEYS)
    np.testing.assert_array_equal(out["endoscope"], obs["endoscope"])
    target = IDENTITY_POSE + 0.01
    np.testing.assert_array_equal(injector.command(target, IDENTITY_POSE), target)


def test_frozen_camera_delivers_the_onset_frame_forever():
    outputs = run(FaultConfig(frozen_camera_step=4), steps=10)
    assert frame_steps(outputs) == [0, 1, 2, 3, 4, 4, 4, 4, 4, 4]
    # The pose keeps updating: only the camera froze.
    assert [o["x.pos"] for o in outputs] == list(range(10))


def test_frozen_camera_thaws_at_the_next_scene():
    injector = FaultInjector(FaultConfig(frozen_camera_step=1))
    first = [injector.observe(observation(k)) for k in range(4)]
    injector.reset(1)
    second = [injector.observe(observation(10 + k)) for k in range(4)]
    assert frame_steps(first) == [0, 1, 1, 1]
    assert frame_steps(second) == [10, 11, 11, 11]


def test_dropped_frames_repeat_the_last_delivered_frame_and_are_seeded():
    config = FaultConfig(dropped_frame_rate=0.5, seed=3)
    injector = FaultInjector(config)
    injector.reset(7)
    outputs = [injector.observe(observation(k)) for k in range(200)]
    delivered = frame_steps(outputs)
    dropped = set(injector.dropped_steps)
    assert 0 not in dropped  # nothing to repeat before the first frame
    assert 60 < len(dropped) < 140
    for k in range(1, 200):
        assert delivered[k] == (delivered[k - 1] if k in dropped else k % 256)
    again = FaultInjector(config)
    again.reset(7)
    assert frame_steps([again.observe(observation(k)) for k in range(200)]) == delivered
    other = FaultInjector(config)
    other.reset(8)
    assert frame_steps([other.observe(observation(k)) for k in range(200)]) != delivered


def test_a_drop_at_the_freeze_step_freezes_the_repeated_frame():
    config = FaultConfig(dropped_frame_rate=0.5, seed=0)
    probe = FaultInjector(config)
    [probe.observe(observation(k)) for k in range(50)]
    onset = next(k for k in probe.dropped_steps if k > 0)
    outputs = run(FaultConfig(dropped_frame_rate=0.5, seed=0, frozen_camera_step=onset), steps=onset + 5)
    delivered = frame_steps(outputs)
    assert delivered[onset] == delivered[onset - 1]
    assert delivered[onset:] == [delivered[onset]] * 5


@settings(max_examples=30, deadline=None)
@given(latency=st.integers(0, 10), steps=st.integers(1, 25))
def test_observation_latency_delays_pose_and_image_together(latency, steps):
    outputs = run(FaultConfig(observation_latency=latency), steps=steps)
    for k, out in enumerate(outputs):
        measured = max(0, k - latency)  # the reset observation stands in at the scene's start
        assert out["x.pos"] == measured and out["jaw.pos"] == measured
        assert int(out["endoscope"][0, 0, 0]) == measured


def test_camera_faults_come_before_the_observation_latency():
    outputs = run(FaultConfig(frozen_camera_step=2, observation_latency=3), steps=9)
    assert [o["x.pos"] for o in outputs] == [0, 0, 0, 0, 1, 2, 3, 4, 5]
    assert frame_steps(outputs) == [0, 0, 0, 0, 1, 2, 2, 2, 2]


def test_observe_never_mutates_its_input_and_returns_copies():
    injector = FaultInjector(FaultConfig(frozen_camera_step=0, observation_latency=1))
    obs = observation(5)
    snapshot = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in obs.items()}
    first = injector.observe(obs)
    second = injector.observe(observation(6))
    assert obs.keys() == snapshot.keys()
    np.testing.assert_array_equal(obs["endoscope"], snapshot["endoscope"])
    assert first["endoscope"] is not obs["endoscope"]
    first["endoscope"][:] = 99  # a caller scribbling on its frame does not reach the stored one
    obs["endoscope"][:] = 77  # nor does the robot reusing its buffer
    third = injector.observe(observation(7))
    assert int(second["endoscope"][0, 0, 0]) == 5 and int(third["endoscope"][0, 0, 0]) == 5


def test_command_latency_holds_then_executes_in_order():
    injector = FaultInjector(FaultConfig(command_latency=3))
    targets = [IDENTITY_POSE + 0.001 * k for k in range(8)]
    measured = [IDENTITY_POSE + 0.0005 * k for k in range(8)]
    executed = [injector.command(t, m) for t, m in zip(targets, measured, strict=True)]
    for k in range(3):
        np.testing.assert_array_equal(executed[k], measured[k])
    for k in range(3, 8):
        np.testing.assert_array_equal(executed[k], targets[k - 3])
    injector.reset(1)  # a new scene holds again until three commands have been sent
    np.testing.assert_array_equal(injector.command(targets[7], measured[0]), measured[0])


def test_command_does_not_keep_a_reference_to_the_target():
    injector = FaultInjector(FaultConfig(command_latency=1))
    target = IDENTITY_POSE.copy()
    injector.command(target, IDENTITY_POSE)
    target[0] = 5.0
    assert injector.command(IDENTITY_POSE, IDENTITY_POSE)[0] == 0.0


def test_arm_lag_goes_part_of_the_way():
    injector = FaultInjector(FaultConfig(arm_lag=0.75))
    measured = IDENTITY_POSE.copy()
    target = measured.copy()
    target[:3] += [0.004, -0.008, 0.002]
    target[9] = 0.0
    c = np.cos(0.4)
    s = np.sin(0.4)
    target[3:9] = [c, s, 0.0, -s, c, 0.0]  # 0.4 rad about z
    out = injector.command(target, measured)
    np.testing.assert_allclose(out[:3], measured[:3] + 0.25 * (target[:3] - measured[:3]))
    assert out[9] == pytest.approx(0.75)
    np.testing.assert_allclose(out[3:9], measured[3:9] + 0.25 * (target[3:9] - measured[3:9]))


def test_arm_lag_falls_back_to_the_commanded_columns_when_they_cancel():
    injector = FaultInjector(FaultConfig(arm_lag=0.5))
    measured = IDENTITY_POSE.copy()
    target = measured.copy()
    target[3:9] = [-1.0, 0.0, 0.0, 0.0, -1.0, 0.0]  # pi about z: halfway the columns are zero
    out = injector.command(target, measured)
    np.testing.assert_array_equal(out[3:9], target[3:9])


def test_command_latency_comes_before_arm_lag():
    injector = FaultInjector(FaultConfig(command_latency=1, arm_lag=0.5))
    measured = IDENTITY_POSE.copy()
    first = IDENTITY_POSE.copy()
    first[0] = 0.01
    np.testing.assert_array_equal(injector.command(first, measured), measured)
    out = injector.command(IDENTITY_POSE + 1.0, measured)
    assert out[0] == pytest.approx(0.005)


@settings(max_examples=50, deadline=None)
@given(
    lag=st.floats(0.0, 0.99),
    delta=st.lists(st.floats(-0.01, 0.01), min_size=3, max_size=3),
    angle=st.floats(-1.0, 1.0),
)
def test_arm_lag_never_overshoots(lag, delta, angle):
    injector = FaultInjector(FaultConfig(arm_lag=lag))
    target = IDENTITY_POSE.copy()
    target[:3] += delta
    target[3:9] = [np.cos(angle), np.sin(angle), 0.0, -np.sin(angle), np.cos(angle), 0.0]
    out = injector.command(target, IDENTITY_POSE)
    step = np.linalg.norm(out[:3] - IDENTITY_POSE[:3])
    assert step <= np.linalg.norm(target[:3] - IDENTITY_POSE[:3]) + 1e-12
    assert step == pytest.approx((1.0 - lag) * np.linalg.norm(delta), abs=1e-12)


def test_command_rejects_wrong_shapes():
    with pytest.raises(ValueError, match="shape"):
        FaultInjector(FaultConfig()).command(np.zeros(9), IDENTITY_POSE)


def test_pose_keys_must_have_ten_entries():
    with pytest.raises(ValueError, match="`pose_keys`"):
        FaultInjector(FaultConfig(), pose_keys=("x.pos",))


def test_derived_keys_are_delayed_with_the_pose_and_the_rest_pass_through():
    """The planned regrasp is seen from the measured pose: a delayed pose carries the regrasp of its own step, while
    the marks (the registration, not measured from the pose) pass through current."""
    injector = FaultInjector(FaultConfig(observation_latency=2), derived_keys=("regrasp_dx.pos",))
    outputs = []
    for k in range(6):
        obs = {**observation(k), "regrasp_dx.pos": 100.0 + k, "entry_x.pos": 200.0 + k}
        outputs.append(injector.observe(obs))
    assert [o["x.pos"] for o in outputs] == [0, 0, 0, 1, 2, 3]
    assert [o["regrasp_dx.pos"] - 100 for o in outputs] == [o["x.pos"] for o in outputs]
    assert [o["entry_x.pos"] - 200 for o in outputs] == list(range(6))
