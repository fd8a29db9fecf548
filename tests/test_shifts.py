"""The distribution shifts of ``lerobot_suture.sim.shifts``: each does what its table says, at the magnitude
asked, on the episode's first observation, and leaves nothing behind for the next episode."""

import math

import gymnasium as gym
import numpy as np
import pytest
from lerobot_suture_studies.robustness import bars, cell_shift_rows

from lerobot_suture.experiments.metrics import most_failures_flagged
from lerobot_suture.registration import ENV_ID
from lerobot_suture.sim.appearance import AppearanceSample
from lerobot_suture.sim.shifts import (
    MAGNITUDES,
    SHIFT_SPECS,
    SHIFTS,
    Shift,
    ShiftWrapper,
    default_shifts,
    within_training_range,
)


def _env(shift: Shift | None = None, **kwargs):
    env = gym.make(ENV_ID, disable_env_checker=True, obs_type="pixels_agent_pos", image_size=64, **kwargs)
    return env if shift is None else ShiftWrapper(env, shift)


def _image(obs) -> np.ndarray:
    return obs["pixels"]["endoscope"].astype(float)


def test_shift_parsing_and_errors_name_the_fix():
    assert Shift.parse("dim_light@0.6") == Shift("dim_light", 0.6)
    assert Shift("action_delay", 2).label == "action_delay@2"
    with pytest.raises(ValueError, match="Unknown shift 'fog'; the shifts are"):
        Shift.parse("fog@0.3")
    with pytest.raises(ValueError, match="NAME@MAGNITUDE"):
        Shift.parse("dim_light")
    with pytest.raises(ValueError, match=r"needs a magnitude in \(0, 0.95\] fraction"):
        Shift("dim_light", 1.5)
    with pytest.raises(ValueError, match="whole control steps"):
        Shift("action_delay", 1.5)
    with pytest.raises(ValueError, match="is not a number"):
        Shift.parse("haze@lots")


def test_every_family_is_covered_at_two_magnitudes_within_its_limits():
    assert {SHIFT_SPECS[s].family for s in SHIFTS} == {"appearance", "sensing", "geometry", "dynamics"}
    assert len(default_shifts()) == 2 * len(SHIFTS)
    for name, (small, large) in MAGNITUDES.items():
        assert 0 < small < large <= SHIFT_SPECS[name].limit


@pytest.mark.parametrize(
    "label, check",
    [
        ("dim_light@0.6", lambda shifted, plain: shifted.mean() < 0.7 * plain.mean()),
        ("smoke_haze@0.6", lambda shifted, plain: shifted.std() < 0.6 * plain.std()),
        ("image_noise@0.1", lambda shifted, plain: np.abs(shifted - plain).mean() > 10),
        ("camera_roll@0.3", lambda shifted, plain: np.abs(shifted - plain).mean() > 5),
        ("tissue_colour@0.15", lambda shifted, plain: np.abs(shifted - plain).mean() > 1),
    ],
)
def test_image_shifts_change_the_first_image(label, check):
    plain, _ = _env().reset(seed=3)
    shifted, _ = _env(Shift.parse(label)).reset(seed=3)
    assert check(_image(shifted), _image(plain))
    np.testing.assert_array_equal(shifted["agent_pos"], plain["agent_pos"])  # the scene is the same


def test_geometry_shifts_move_the_phantom_by_the_magnitude():
    plain = _env()
    plain.reset(seed=5)
    raised = _env(Shift("phantom_raised", 0.008))
    raised.reset(seed=5)
    turned = _env(Shift("phantom_turned", 0.5))
    turned.reset(seed=5)
    p, r, t = plain.unwrapped, raised.unwrapped, turned.unwrapped
    np.testing.assert_allclose(r.phantom_position - p.phantom_position, [0.0, 0.0, 0.008], atol=1e-12)
    assert t.phantom_yaw - p.phantom_yaw == pytest.approx(0.5)


def test_state_noise_is_on_what_the_policy_reads_only_and_seeded():
    env, plain = _env(Shift("state_noise", 0.002)), _env()
    obs, _ = env.reset(seed=1)
    ref, _ = plain.reset(seed=1)
    offset = obs["agent_pos"][:3] - ref["agent_pos"][:3]
    assert 0 < np.abs(offset).max() < 0.01
    np.testing.assert_array_equal(obs["agent_pos"][3:], ref["agent_pos"][3:])
    again, _ = env.reset(seed=1)
    np.testing.assert_array_equal(again["agent_pos"], obs["agent_pos"])


def test_action_delay_executes_each_command_late():
    delayed, plain = _env(Shift("action_delay", 2)), _env()
    obs, _ = delayed.reset(seed=2)
    plain.reset(seed=2)
    hold = obs["agent_pos"].copy()
    command = hold.copy()
    command[2] += 0.004  # 4 mm up
    # The delayed env first executes two holds, then the command: as the plain env does when told so.
    for _ in range(3):
        out, *_ = delayed.step(command)
    for action in (hold, hold, command):
        ref, *_ = plain.step(action)
    np.testing.assert_allclose(out["agent_pos"], ref["agent_pos"], atol=1e-6)


def test_a_set_look_is_undone_at_the_next_reset():
    fresh, _ = _env().reset(seed=4)
    env = _env()
    env.reset(seed=0)
    env.unwrapped.set_appearance(AppearanceSample(light_scale=0.3, haze=0.5, camera_roll=0.2))
    dimmed = env.unwrapped.observe()
    assert _image(dimmed).mean() != pytest.approx(_image(fresh).mean(), abs=1)
    again, _ = env.reset(seed=4)
    np.testing.assert_array_equal(again["pixels"]["endoscope"], fresh["pixels"]["endoscope"])


def test_the_range_status_follows_the_dataset_appearance():
    recipe = {"light_intensity": 0.3, "haze": 0.3, "noise": 0.0}
    assert within_training_range(Shift("dim_light", 0.2), recipe) is True
    assert within_training_range(Shift("dim_light", 0.6), recipe) is False
    assert within_training_range(Shift("image_noise", 0.02), recipe) is None  # the recipe leaves noise off
    assert within_training_range(Shift("action_delay", 1), recipe) is None
    assert within_training_range(Shift("dim_light", 0.2), None) is None


def test_leaderboard_cells_give_the_reports_rows():
    cell = {"episodes": 50, "successes": 40, "success_rate": 0.8, "success_interval": [0.67, 0.89],
            "gate": {"flagged": 12, "flagged_rate": 0.24, "flagged_failures": 9, "failures": 10}}  # fmt: skip
    row = {
        "nominal": cell,
        "shift:dim_light@0.2": cell,
        "shift:dim_light@0.6": {**cell, "successes": 50, "success_rate": 1.0},
    }
    rows = cell_shift_rows(row, {"light_intensity": 0.3})
    assert [(r["shift"], r["range"]) for r in rows] == [
        ("dim_light@0.2", "inside"),
        ("dim_light@0.6", "beyond"),
    ]
    assert rows[0]["flagged_of_failures"] == 0.9 and rows[0]["flagged_of_successes"] == 3 / 40
    assert rows[0]["success_interval"] == [0.67, 0.89]
    assert math.isnan(rows[1]["flagged_of_failures"])  # no failed run to flag
    with pytest.raises(ValueError, match="no gate"):
        cell_shift_rows({"shift:dim_light@0.2": {**cell, "gate": None}}, None)


def test_bars_pool_the_flags_over_runs_beyond_the_range():
    rows = [
        {"range": "inside", "runs": 10, "failures": 1, "success_rate": 0.9,
         "flagged_of_failures": 1.0, "flagged_of_successes": 0.0},
        {"range": "beyond", "runs": 10, "failures": 8, "success_rate": 0.2,
         "flagged_of_failures": 1.0, "flagged_of_successes": 0.5},
        {"range": "untrained", "runs": 10, "failures": 2, "success_rate": 0.8,
         "flagged_of_failures": 0.5, "flagged_of_successes": 0.0},
    ]  # fmt: skip
    b = bars(rows, None)
    assert b["min_success_inside_range"] == 0.9
    assert b["beyond_failed_runs"] == 10
    assert b["beyond_flagged_of_failures"] == pytest.approx((8 * 1.0 + 2 * 0.5) / 10)
    assert b["beyond_flagged_of_successes"] == pytest.approx((2 * 0.5 + 8 * 0.0) / 10)
    assert math.isnan(b["beyond_failure_auroc"])  # a benchmark that kept no per-run scores
    # With per-run maxima: failures 3, 5, 9 and successes 1, 4 beyond the ranges.
    rows[1] |= {"run_max_scores": [3.0, 5.0, 4.0], "run_successes": [False, False, True]}
    rows[2] |= {"run_max_scores": [9.0, 1.0], "run_successes": [False, True]}
    b = bars(rows, None)
    assert b["beyond_failure_auroc"] == pytest.approx(5 / 6)  # 3 < 4: one pair of six out of order
    assert b["beyond_most_failures_flagged_at_bar"] == pytest.approx(2 / 3)  # above 4: 5 and 9


def test_most_failures_flagged_is_the_best_threshold_in_hindsight():
    failed, succeeded = [2.0, 6.0, 7.0, 8.0], [1.0, 3.0, 5.0, 9.0]
    assert most_failures_flagged(failed, succeeded, 0.0) == 0.0  # nothing above the largest success, 9
    assert most_failures_flagged(failed, succeeded, 0.25) == 0.75  # above 5: 6, 7, 8 (9 flagged too)
    assert most_failures_flagged(failed, succeeded, 0.5) == 0.75  # above 3 as well: still 6, 7, 8
    assert most_failures_flagged(failed, succeeded, 1.0) == 1.0
    assert most_failures_flagged(failed, [5.0, 5.0], 0.5) == 0.75  # a tie lets neither success through
    assert math.isnan(most_failures_flagged([], succeeded, 0.15))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        most_failures_flagged(failed, succeeded, 1.5)
