"""The surgeon in the loop: LeRobot's teleoperators driven by scripts, takeover, recorded runs and merging."""

import json
import logging
import os
import shutil

import gymnasium as gym
import numpy as np
import pytest
import torch

import lerobot_suture
from lerobot_suture.datasets.merge import merge_runs
from lerobot_suture.datasets.video import resolve_video_backend
from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy
from lerobot_suture.runtime.takeover import Actor, Takeover
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.safety.ood.calibration import fit_calibration
from lerobot_suture.safety.ood.calibration_file import save_calibration
from lerobot_suture.surgeon.record_run import (
    ACTOR_KEY,
    GATE_DECISION_KEY,
    IS_INTERVENTION_KEY,
    UNCERTAINTY_KEY,
    RunRecorder,
    label_demonstrations,
)
from lerobot_suture.surgeon.scripted_input import GamepadScript, KeyScript
from lerobot_suture.surgeon.session import gate_decision, run_surgeon_episode
from lerobot_suture.surgeon.surgeons import (
    ExpertSurgeon,
    GamepadSurgeon,
    KeyboardSurgeon,
    NoSurgeon,
    gamepad_teleop,
    keyboard_teleop,
    make_surgeon,
)
from lerobot_suture.surgeon.teleop_mapping import TeleopMappingConfig, initial_target, step_target

P, S, H = Actor.POLICY, Actor.SURGEON, Actor.HOLD


def _runner(policy_dir, tmp_path, threshold: float, enforce: bool = True) -> PolicyRunner:
    """The tiny policy with a gate whose threshold sits at `threshold` (tiny: O.O.D. at once)."""
    directory = tmp_path / "policy"
    shutil.copytree(policy_dir, directory)
    scores = threshold * (1 + 1e-3 * np.random.default_rng(0).standard_normal(100))
    config = json.loads((directory / "config.json").read_text())
    filename = config.get("ood", {}).get("calibration_file", "ood_calibration.json")
    save_calibration(fit_calibration(np.abs(scores), model="normal"), directory, filename=filename)
    return PolicyRunner.from_pretrained(directory, GateMode.of(enforce))


def _env(runner, cbf: bool = True):
    return gym.make(
        lerobot_suture.ENV_ID,
        disable_env_checker=True,
        cbf=CBFConfig(enabled=True) if cbf else None,
        **env_kwargs_for_policy(runner.policy.config),
    )


# ------------------------------------------------------------------ pure parts


def test_mapping_integrates_commands_and_clips_to_the_workspace():
    config = TeleopMappingConfig(translation_speed=0.01, rotation_speed=1.0)
    target = initial_target(np.array([0.0, 0.0, 0.02, 1, 0, 0, 0, 1, 0, 0.88]))
    assert target[9] == 1.0  # a holding jaw (reads 0.88) is commanded closed
    moved = step_target(target, {"delta_x": 1, "delta_z": -1, "gripper": 1}, np.array([0, 0, 1.0]), config)
    np.testing.assert_allclose(moved[:3], [0.001, 0.0, 0.019])  # 10 mm/s for 0.1 s
    np.testing.assert_allclose(moved[3:6], [np.cos(0.1), np.sin(0.1), 0], atol=1e-12)  # 1 rad/s about z
    assert step_target(moved, {"gripper": 2}, None, config)[9] == 0.0  # LeRobot's "open"
    far = target.copy()
    far[:3] = [0.0499, 0.0, 0.0001]
    assert np.allclose(step_target(far, {"delta_x": 1, "delta_z": -1}, None, config)[:3], [0.05, 0, 0])
    with pytest.raises(ValueError, match="`translation_speed` must be in"):
        TeleopMappingConfig(translation_speed=0.0)
    with pytest.raises(ValueError, match="finite"):
        step_target(target, {"delta_x": float("nan")}, None, config)


def test_takeover_transitions():
    t = Takeover(has_surgeon=True)
    assert t.update(0, released=False, take_over=False, hand_back=False) is P
    assert t.update(1, released=False, take_over=True, hand_back=False) is S
    assert t.update(2, released=True, take_over=False, hand_back=False) is S
    assert t.update(3, released=False, take_over=False, hand_back=True) is P
    assert t.update(4, released=True, take_over=False, hand_back=False) is S
    assert [h[3] for h in t.handovers] == ["taken over", "handed back", "gate released"]
    nobody = Takeover(has_surgeon=False)
    assert nobody.update(0, released=False, take_over=True, hand_back=False) is P  # nobody to take over
    assert nobody.update(1, released=True, take_over=False, hand_back=False) is H


def test_unknown_surgeon_and_headless_keyboard_are_refused(monkeypatch):
    with pytest.raises(ValueError, match="`surgeon` must be one of"):
        make_surgeon("robot")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(ValueError, match="needs a display"):
        make_surgeon("keyboard")


# ------------------------------------------------------------------ LeRobot's teleoperators, scripted


def test_keyboard_takes_over_turns_and_hands_back(tiny_policy_dir, tmp_path):
    """LeRobot's KeyboardEndEffectorTeleop, fed keys through its own listener callbacks: `t` takes over from
    a policy the gate keeps in control, `i` turns the jaw, `p` hands back, `s` is LeRobot's success."""
    runner = _runner(tiny_policy_dir, tmp_path, threshold=1e6)  # never O.O.D.
    teleop = keyboard_teleop()
    surgeon = KeyboardSurgeon(teleop, TeleopMappingConfig(rotation_speed=1.0))
    script = KeyScript(teleop, {2: ["t"], 3: ["i"], 4: ["i"], 5: ["p"], 7: ["s"]})
    env = _env(runner)
    log = run_surgeon_episode(env, runner, surgeon, seed=0, max_steps=20, script=script)
    surgeon.close()
    assert log.actors == [P, P, S, S, S, P, P, P]
    assert log.stop_reason == "teleop event"  # LeRobot's `s` (success) event ends the episode
    assert [(h[0], h[3]) for h in log.handovers] == [(2, "taken over"), (5, "handed back")]
    assert all(np.isnan(s.score) and gate_decision(s) == -1 for s in log.steps[2:5])  # the policy not asked
    assert all(gate_decision(s) == 0 for s in log.steps[:2] + log.steps[5:])  # re-armed, in distribution


def test_gamepad_moves_the_jaw_through_the_cbf_wrapped_env(tiny_policy_dir, tmp_path):
    """LeRobot's GamepadTeleop with a scripted joystick: the gate releases control at once, RB is not
    needed; the left stick moves the jaw tip 0.5 mm per step along world x; LB hands back."""
    runner = _runner(tiny_policy_dir, tmp_path, threshold=1e-12)  # O.O.D. at once
    teleop = gamepad_teleop()
    teleop.connect()
    surgeon = GamepadSurgeon(teleop)
    push = {"axes": {1: -1.0}}  # LeRobot: delta_x = -axis 1
    script = GamepadScript(teleop, {0: push, 1: push, 2: push, 3: {"buttons": [4]}})
    env = _env(runner)
    log = run_surgeon_episode(env, runner, surgeon, seed=1, max_steps=4, script=script)
    assert log.actors[:3] == [S, S, S] and log.handovers[0][3] == "gate released"
    assert log.actors[3] is P  # handed back: the re-armed gate releases again, the policy's hold action
    start = _env(runner).reset(seed=1)[0]["agent_pos"][:3]
    end = env.unwrapped.jaw_pose()[0]
    assert 1.0e-3 < end[0] - start[0] < 1.6e-3  # 3 steps of 0.5 mm along world x, through the CBF wrapper
    assert np.all(np.abs(end[1:] - start[1:]) < 2e-4)
    surgeon.close()


def test_without_a_policy_the_surgeon_drives_from_the_first_step():
    """``lerobot-suture teleop`` is the same episode loop with no policy: the gamepad drives every step, no
    handover is logged, and the gate is never consulted; nobody at all is refused."""
    teleop = gamepad_teleop()
    teleop.connect()
    surgeon = GamepadSurgeon(teleop)
    push = {"axes": {1: -1.0}}
    env = gym.make(lerobot_suture.ENV_ID, disable_env_checker=True, obs_type="state")
    start = env.reset(seed=3)[0]["agent_pos"][0]
    log = run_surgeon_episode(
        env, None, surgeon, 3, 3, script=GamepadScript(teleop, {0: push, 1: push, 2: push})
    )
    assert log.actors == [S] * 3 and not log.handovers and log.stop_reason == "max_steps"
    assert all(gate_decision(s) == -1 for s in log.steps)
    assert 1.0e-3 < env.unwrapped.jaw_pose()[0][0] - start < 1.6e-3
    with pytest.raises(ValueError, match="a surgeon must drive"):
        run_surgeon_episode(env, None, NoSurgeon(), 0, 2)
    surgeon.close()


# ------------------------------------------------------------------ interventions are data


def _record_demo(root, image_size: int):
    from lerobot_suture.datasets.record import record
    from lerobot_suture.datasets.record_config import RecordConfig

    cfg = RecordConfig(
        repo_id="suture-tests/demo", root=str(root), num_episodes=1, val_fraction=0.0, image_size=image_size
    )
    record(cfg)


def test_recorded_run_loads_in_lerobot_and_merges_with_demonstrations(tiny_policy_dir, tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    runner = _runner(tiny_policy_dir, tmp_path, threshold=1e6)  # in distribution
    kwargs = env_kwargs_for_policy(runner.policy.config)
    assert kwargs["obs_type"] == "pixels_agent_pos"
    recorder = RunRecorder("suture-tests/run", tmp_path / "run", kwargs["obs_type"], kwargs["image_size"])
    env = _env(runner)
    teleop = keyboard_teleop()
    script = KeyScript(teleop, {2: ["t"], 4: ["p"]})
    log_k = run_surgeon_episode(env, runner, KeyboardSurgeon(teleop), 0, 6, recorder=recorder, script=script)
    expert_runner = _runner(tiny_policy_dir, tmp_path / "released", threshold=1e-12)
    log_e = run_surgeon_episode(env, expert_runner, ExpertSurgeon(), 1, 3, recorder=recorder)
    log_n = run_surgeon_episode(env, expert_runner, NoSurgeon(), 2, 2, recorder=recorder)
    recorder.finalize()
    assert log_k.actors == [P, P, S, S, P, P] and log_e.actors == [S] * 3 and log_n.actors == [H] * 2

    run = LeRobotDataset("suture-tests/run", root=tmp_path / "run", video_backend=resolve_video_backend())
    assert run.meta.total_episodes == 3 and run.meta.total_frames == 11
    frames = [run[i] for i in range(len(run))]
    actors = [int(f[ACTOR_KEY]) for f in frames]
    assert actors == [0, 0, 1, 1, 0, 0, 1, 1, 1, 2, 2]
    assert [float(f[IS_INTERVENTION_KEY]) for f in frames] == [float(a == 1) for a in actors]
    decisions = [int(f[GATE_DECISION_KEY]) for f in frames]
    assert decisions == [0, 0, -1, -1, 0, 0, 1, -1, -1, 1, -1]  # the release's step says O.O.D.
    scores = np.array([float(f[UNCERTAINTY_KEY]) for f in frames])
    assert np.isfinite(scores[[0, 1, 4, 5, 6, 9]]).all() and np.isnan(scores[[2, 3, 7, 8, 10]]).all()
    assert frames[0]["observation.images.endoscope"].shape == (3, kwargs["image_size"], kwargs["image_size"])

    # The demonstrations get the same label columns (LeRobot's add_features); then LeRobot's merge.
    _record_demo(tmp_path / "demo", kwargs["image_size"])  # features must agree: the same image size
    demo = LeRobotDataset("suture-tests/demo", root=tmp_path / "demo", video_backend=resolve_video_backend())
    labelled = label_demonstrations(demo, tmp_path / "demo_labelled", "suture-tests/demo_labelled")
    scheduling = os.sched_getscheduler(0)
    merge_runs([labelled, run], "suture-tests/merged", tmp_path / "merged")
    assert os.sched_getscheduler(0) == scheduling  # the video encoder did not leave the thread real-time
    merged = LeRobotDataset(
        "suture-tests/merged", root=tmp_path / "merged", video_backend=resolve_video_backend()
    )
    assert merged.meta.total_episodes == demo.meta.total_episodes + 3
    assert merged.meta.total_frames == demo.meta.total_frames + 11
    tail = [merged[len(merged) - 11 + i] for i in range(11)]
    assert [int(f[ACTOR_KEY]) for f in tail] == actors
    assert int(merged[0][ACTOR_KEY]) == 1 and int(merged[0][GATE_DECISION_KEY]) == -1
    # The scores the policy was not asked for stay NaN, and lerobot-train's collate batches them.
    batch = torch.utils.data.default_collate(tail)
    merged_scores = batch[UNCERTAINTY_KEY].numpy().ravel()
    np.testing.assert_array_equal(np.isnan(merged_scores), np.isnan(scores))


# ------------------------------------------------------------------ the commands


def test_surgeon_run_command_records_and_writes_the_live_view(tiny_policy_dir, tmp_path, capsys):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_suture.cli import main as cli_main

    runner = _runner(tiny_policy_dir, tmp_path, threshold=1e-12)  # O.O.D. at once: the expert takes over
    del runner
    view = tmp_path / "view.rrd"
    cli_main(
        [
            "surgeon-run",
            f"--policy.path={tmp_path / 'policy'}",
            "--surgeon=expert",
            "--max_steps=3",
            "--display=false",
            f"--view_path={view}",
            f"--record_root={tmp_path / 'run'}",
            "--video=false",
        ]
    )
    run = LeRobotDataset("local/suture_surgeon_run", root=tmp_path / "run")
    assert [int(run[i][ACTOR_KEY]) for i in range(len(run))] == [1, 1, 1]
    assert view.stat().st_size > 1000  # images, the trace and who is in control
    with pytest.raises(SystemExit) as exit_info:
        cli_main(["surgeon-run", f"--policy.path={tmp_path / 'policy'}", "--surgeon=robot"])
    assert exit_info.value.code == 2
    assert "`surgeon` must be one of" in capsys.readouterr().err


def test_surgeon_run_without_a_display_says_so_once_and_carries_on(
    tiny_policy_dir, tmp_path, monkeypatch, caplog
):
    """As a new user runs it on a machine without a display: the default (show the live view) turns the
    view off with one warning, the episodes run and the recording is saved."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_suture.cli import main as cli_main

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    _runner(tiny_policy_dir, tmp_path, threshold=1e-12)  # writes the calibrated copy under tmp_path/policy
    args = ["surgeon-run", f"--policy.path={tmp_path / 'policy'}", "--surgeon=expert", "--max_steps=2"]
    with caplog.at_level(logging.WARNING, logger="lerobot_suture.surgeon.live_view"):
        cli_main([*args, f"--record_root={tmp_path / 'run'}", "--video=false"])
    warnings = [r.getMessage() for r in caplog.records if r.name == "lerobot_suture.surgeon.live_view"]
    assert len(warnings) == 1 and "live view off: no display" in warnings[0] and "--view_path" in warnings[0]
    assert len(LeRobotDataset("local/suture_surgeon_run", root=tmp_path / "run")) == 2


def test_surgeon_run_with_an_uncalibrated_policy_names_the_fix_before_any_view(tiny_policy_dir, capsys):
    from lerobot_suture.cli import main as cli_main

    with pytest.raises(SystemExit) as exit_info:
        cli_main(["surgeon-run", f"--policy.path={tiny_policy_dir}", "--surgeon=expert", "--max_steps=2"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "lerobot-suture calibrate --policy.path=" in err and len(err.strip().splitlines()) == 1


def test_teleop_command_records_the_surgeon_driving_every_step(tmp_path, monkeypatch):
    """``lerobot-suture teleop``, as a user runs it, with LeRobot's gamepad on a scripted stick (no device here):
    one recorded episode whose every frame is the surgeon's, the gate never consulted."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    import lerobot_suture.surgeon.run as run_module
    from lerobot_suture.cli import main as cli_main

    def scripted_gamepad(name, mapping=None):
        teleop = gamepad_teleop()
        teleop.connect()
        GamepadScript(teleop, {})  # a stick at rest
        return GamepadSurgeon(teleop, mapping)

    monkeypatch.setattr(run_module, "make_surgeon", scripted_gamepad)
    root = tmp_path / "teleop"
    cli_main(
        ["teleop", "--teleop=gamepad", "--episodes=1", "--max_steps=3", "--display=false"]
        + [f"--record_root={root}", "--video=false", "--image_size=32"]
    )
    frames = LeRobotDataset("local/suture_surgeon_run", root=root)
    assert len(frames) == 3
    assert [int(frames[i][ACTOR_KEY]) for i in range(3)] == [1, 1, 1]
    assert [int(frames[i][GATE_DECISION_KEY]) for i in range(3)] == [-1, -1, -1]
