"""The stale-camera watchdog: validation, its rule on synthetic streams, and nominal vs frozen expert episodes."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lerobot_suture.safety.camera_watchdog import (
    CameraWatchdog,
    CameraWatchdogConfig,
    rotation_angle,
)

HOME = np.array([0.0, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 1.0])


def pose_at(step: int, speed: float = 0.002, turn: float = 0.0) -> np.ndarray:
    """The pose after ``step`` steps moving along x at ``speed`` (m/step), turning ``turn`` (rad/step) about z."""
    pose = HOME.copy()
    pose[0] += speed * step
    angle = turn * step
    pose[3:9] = [math.cos(angle), math.sin(angle), 0.0, -math.sin(angle), math.cos(angle), 0.0]
    return pose


def frame(value: int) -> np.ndarray:
    return np.full((8, 8, 3), value % 256, dtype=np.uint8)


def feed(watchdog: CameraWatchdog, frames, poses) -> list[bool]:
    return [watchdog.update(f, p) for f, p in zip(frames, poses, strict=True)]


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("min_motion", 0.0, "`min_motion` must be in (0, inf) m. Got 0.0."),
        ("min_rotation", -0.1, "`min_rotation` must be in (0, inf) rad. Got -0.1."),
        ("patience", 0, "`patience` must be >= 1. Got 0."),
    ],
)
def test_config_rejects_out_of_range(field, value, message):
    with pytest.raises(ValueError) as error:
        CameraWatchdogConfig(**{field: value})
    assert str(error.value) == message


def test_rotation_angle():
    assert rotation_angle(pose_at(0)[3:9], pose_at(1, turn=0.3)[3:9]) == pytest.approx(0.3)
    assert rotation_angle(HOME[3:9], HOME[3:9]) == pytest.approx(0.0, abs=1e-7)
    assert math.isnan(rotation_angle(np.zeros(6), HOME[3:9]))


def test_frozen_frame_on_a_moving_arm_is_flagged_after_patience_steps():
    watchdog = CameraWatchdog()
    frames = [frame(k) for k in range(5)] + [frame(4)] * 5
    flags = feed(watchdog, frames, [pose_at(k) for k in range(10)])
    assert flags == [False] * 6 + [True] * 4
    assert watchdog.flagged_at == 6
    # Flagged stays flagged, even once the frames change again; reset clears it.
    assert watchdog.update(frame(200), pose_at(11))
    watchdog.reset()
    assert watchdog.flagged_at is None and watchdog.stale_steps == 0
    assert not watchdog.update(frame(200), pose_at(12))


def test_rotation_alone_counts_as_moving():
    watchdog = CameraWatchdog()
    flags = feed(watchdog, [frame(0)] * 4, [pose_at(k, speed=0.0, turn=0.05) for k in range(4)])
    assert flags == [False, False, True, True]
    slow = CameraWatchdog()
    assert not any(feed(slow, [frame(0)] * 4, [pose_at(k, speed=0.0, turn=0.02) for k in range(4)]))


def test_a_still_arm_never_flags_a_frozen_frame_nor_clears_a_run():
    still = CameraWatchdog()
    assert not any(feed(still, [frame(0)] * 30, [HOME] * 30))
    assert still.stale_steps == 0
    watchdog = CameraWatchdog(CameraWatchdogConfig(patience=3))
    poses = [pose_at(0), pose_at(1), pose_at(2), pose_at(2), pose_at(2), pose_at(3)]
    frames = [frame(0), frame(0), frame(0), frame(0), frame(9), frame(9)]
    # Two stale moving steps, two still steps (one with a new frame) that cannot tell, a third stale one.
    assert feed(watchdog, frames, poses) == [False] * 5 + [True]
    assert watchdog.flagged_at == 5


def test_changing_frames_on_a_moving_arm_never_flag():
    watchdog = CameraWatchdog()
    assert not any(feed(watchdog, [frame(k) for k in range(50)], [pose_at(k) for k in range(50)]))
    assert watchdog.stale_steps == 0


def test_a_live_moving_step_resets_the_run():
    watchdog = CameraWatchdog(CameraWatchdogConfig(patience=2))
    frames = [frame(0), frame(0), frame(1), frame(1), frame(2)]
    assert not any(feed(watchdog, frames, [pose_at(k) for k in range(5)]))


def test_missing_or_empty_frames_are_stale_even_on_a_still_arm():
    watchdog = CameraWatchdog()
    assert not watchdog.update(None, HOME)
    assert watchdog.update(np.zeros((0, 0, 3), dtype=np.uint8), HOME)
    assert watchdog.flagged_at == 1


def test_a_reused_buffer_is_compared_by_content():
    watchdog = CameraWatchdog()
    buffer = frame(0)
    for k in range(10):
        buffer[:] = k  # the caller writes each new frame into the same array
        assert not watchdog.update(buffer, pose_at(k))


def test_pose_must_have_ten_entries():
    with pytest.raises(ValueError, match="`pose`"):
        CameraWatchdog().update(frame(0), np.zeros(9))


@settings(max_examples=40, deadline=None)
@given(onset=st.integers(1, 30), patience=st.integers(1, 5), extra=st.integers(0, 10))
def test_a_freeze_on_a_moving_arm_flags_exactly_patience_steps_later(onset, patience, extra):
    steps = onset + patience + extra + 1
    watchdog = CameraWatchdog(CameraWatchdogConfig(patience=patience))
    frames = [frame(min(k, onset)) for k in range(steps)]
    feed(watchdog, frames, [pose_at(k) for k in range(steps)])
    assert watchdog.flagged_at == onset + patience


def expert_episode(seed: int, freeze_at: int | None = None) -> tuple[CameraWatchdog, int]:
    """The scripted expert's insertion of ``seed`` watched; the frame frozen from ``freeze_at`` on."""
    from lerobot_suture.expert import ScriptedExpert
    from lerobot_suture.sim.suture_env import SutureEnv

    env = SutureEnv(image_size=64)
    try:
        obs, _ = env.reset(seed=seed)
        expert = ScriptedExpert()
        expert.reset(env)
        watchdog = CameraWatchdog()
        frozen = None
        step = 0
        while True:
            image = obs["pixels"]["endoscope"]
            if freeze_at is not None and step == freeze_at:
                frozen = image.copy()
            watchdog.update(frozen if frozen is not None else image, obs["agent_pos"])
            obs, _reward, terminated, truncated, _info = env.step(expert.act(env))
            step += 1
            if terminated or truncated:
                return watchdog, step
    finally:
        env.close()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_expert_episodes_flag_only_a_frozen_endoscope(seed):
    nominal, steps = expert_episode(seed)
    assert steps > 20
    assert nominal.flagged_at is None
    frozen, _ = expert_episode(seed, freeze_at=10)
    assert frozen.flagged_at is not None and 10 < frozen.flagged_at <= 15
