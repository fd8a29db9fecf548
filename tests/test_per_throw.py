"""The running suture throw by throw: the per-throw record of a rollout, and the table made of it."""

import json
import math
import shutil

import numpy as np
import pytest

from lerobot_suture.experiments.per_throw import per_throw_table, plot_per_throw, throw_outcome
from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy
from lerobot_suture.runtime.rollout import EpisodeLog, StepLog, make_scenario_env, rollout_episode
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.safety.ood.calibration import fit_calibration
from lerobot_suture.safety.ood.calibration_file import save_calibration
from lerobot_suture.sim.running_suture import N_THROWS


def _step(throw: int, ood: bool = False, active: bool = False, h: float = math.nan) -> StepLog:
    return StepLog(
        score=0.0,
        threshold=1.0,
        ood=ood,
        released=False,
        new_prediction=True,
        controller="policy",
        perturbed=False,
        needle_in_tissue=False,
        cbf_active=active,
        cbf_intervened=active and h < 1e-3,
        h_min_physics=h,
        throw_index=throw,
    )


def _result(throw: int, on_marks: bool, extracted: bool) -> dict:
    error = 0.001 if on_marks else 0.004
    return {
        "throw": throw,
        "entry_error_m": 0.001,
        "exit_error_m": error,
        "on_marks": on_marks,
        "extracted": extracted,
    }


def _episodes() -> list[EpisodeLog]:
    # All four throws on the marks, no alarm; the CBF active on the first throw.
    whole = EpisodeLog(seed=0, scenario="nominal", success=True)
    whole.steps = [_step(0, active=True, h=0.002), _step(0, active=True, h=0.0005)] + [
        _step(k) for k in (1, 2, 3)
    ]
    whole.throw_results = [_result(k, True, k < 3) for k in range(4)]
    # The second throw off the marks; the gate's first alarm came during it.
    off = EpisodeLog(seed=1, scenario="nominal")
    off.steps = [_step(0), _step(1), _step(1, ood=True)]
    off.throw_results = [_result(0, True, True), _result(1, False, False)]
    # The first throw on the marks but never extracted; the gate alarmed during the first throw.
    stuck = EpisodeLog(seed=2, scenario="nominal")
    stuck.steps = [_step(0, ood=True), _step(0, ood=True)]
    stuck.throw_results = [_result(0, True, False)]
    # The first throw never over.
    unfinished = EpisodeLog(seed=3, scenario="nominal")
    unfinished.steps = [_step(0, active=True, h=-1e-4)]
    return [whole, off, stuck, unfinished]


def test_each_throw_is_reached_on_the_marks_off_them_or_unfinished():
    whole, off, stuck, unfinished = _episodes()
    assert [throw_outcome(whole, k) for k in range(4)] == ["on_marks"] * 4
    assert [throw_outcome(off, k) for k in range(3)] == ["on_marks", "off_marks", "not_reached"]
    assert [throw_outcome(stuck, k) for k in range(2)] == ["on_marks", "not_reached"]
    assert throw_outcome(unfinished, 0) == "unfinished"


def test_the_table_counts_every_throw_and_what_the_gate_and_the_cbf_did(tmp_path):
    table = per_throw_table(_episodes(), N_THROWS)
    first, second, third, fourth = table["throws"]
    assert [t["reached"] for t in table["throws"]] == [4, 2, 1, 1]
    assert first["on_marks"]["count"] == 3 and first["on_marks"]["of"] == 4 and first["unfinished"] == 1
    assert second["on_marks_when_reached"]["count"] == 1 and second["off_marks"] == 1
    assert fourth["on_marks"]["rate"] == 0.25
    assert table["all_throws_on_marks"]["count"] == 1
    lo, hi = table["all_throws_on_marks"]["wilson_95"]
    assert lo < 0.25 < hi
    # The gate: on the first throw it alarmed on one of the three on the marks (the stuck episode's) and not
    # on the unfinished one; on the second it alarmed on the throw off the marks.
    assert (
        first["gate"]["alarmed_on_throw_on_marks"]["count"],
        first["gate"]["alarmed_on_throw_on_marks"]["of"],
    ) == (1, 3)
    assert (
        first["gate"]["alarmed_on_failed_throw"]["count"],
        first["gate"]["alarmed_on_failed_throw"]["of"],
    ) == (0, 1)
    assert second["gate"]["alarmed_on_failed_throw"]["count"] == 1
    assert first["gate"]["first_alarm_here"] == 1 and second["gate"]["first_alarm_here"] == 1
    assert table["episodes_with_an_alarm"] == 2
    # The CBF: the smallest barrier value of the first throw, and its violation, counted there only.
    assert first["cbf"]["active_steps"] == 3 and first["cbf"]["steps_with_violation"] == 1
    assert first["cbf"]["h_min_physics"] == pytest.approx(-1e-4)
    assert third["cbf"]["active_steps"] == 0 and third["cbf"]["h_min_physics"] is None
    assert second["exit_error_mm"]["max"] == pytest.approx(4.0)
    assert plot_per_throw(table, tmp_path / "per_throw.png", "test").stat().st_size > 0


def test_a_rollout_records_the_throws_and_the_expert_takes_over_the_whole_suture(tiny_policy_dir, tmp_path):
    """Released at once (a gate fitted so that everything is O.O.D.), the scripted surgeon sutures all four
    throws under the CBF; the rollout's log holds each throw's steps and record."""
    directory = tmp_path / "policy"
    shutil.copytree(tiny_policy_dir, directory)
    scores = 1e-12 * (1 + 1e-3 * np.random.default_rng(0).standard_normal(100))
    save_calibration(fit_calibration(np.abs(scores)), directory)
    runner = PolicyRunner.from_pretrained(directory, GateMode.ENFORCE)
    env_kwargs = {**env_kwargs_for_policy(runner.policy.config), "task": "running_suture"}
    env = make_scenario_env(env_kwargs, "nominal", CBFConfig(enabled=True), trace=True)
    log = rollout_episode(env, runner, seed=0, surgeon="expert")
    assert log.success and log.handover_step == 0
    assert [r["on_marks"] for r in log.throw_results] == [True] * N_THROWS
    assert sorted({s.throw_index for s in log.steps}) == list(range(N_THROWS))
    table = per_throw_table([log], N_THROWS)
    assert [t["on_marks"]["count"] for t in table["throws"]] == [1] * N_THROWS
    assert [t["extracted"] for t in table["throws"]] == [1, 1, 1, 0]
    for throw in table["throws"]:
        assert throw["cbf"]["active_steps"] > 0
        assert throw["cbf"]["h_min_physics"] >= 0.0
    assert table["throws"][0]["gate"]["first_alarm_here"] == 1


def test_the_committed_table_is_the_rendering_of_the_committed_result():
    from pathlib import Path

    from lerobot_suture.experiments.per_throw import per_throw_markdown

    folder = Path(__file__).resolve().parents[1] / "docs" / "results" / "running_suture"
    result = json.loads((folder / "per_throw.json").read_text())["result"]
    assert (folder / "per_throw.md").read_text() == per_throw_markdown(result)
    assert (folder / "per_throw.md").read_text() in (folder.parents[1] / "results.md").read_text()
