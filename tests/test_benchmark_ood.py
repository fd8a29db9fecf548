"""``lerobot-suture benchmark-ood`` end to end at toy scale: every file it writes and what is in it, and
a second run that reuses the saved rollout parts."""

import json
import math
import shutil

import numpy as np
import pytest
from lerobot_suture_studies.benchmark_ood import SCENARIOS, BenchmarkOODConfig
from PIL import Image

from lerobot_suture.cli import main as cli_main
from lerobot_suture.detectors import DETECTOR_NAMES
from lerobot_suture.runtime.config import PolicyPathConfig


def test_benchmark_config_names_the_field_and_range(tiny_policy_dir):
    with pytest.raises(ValueError, match="`calibration_episodes` >= 19"):
        BenchmarkOODConfig(policy=PolicyPathConfig(path=tiny_policy_dir), calibration_episodes=5)
    with pytest.raises(ValueError, match="`detectors` must name some of"):
        BenchmarkOODConfig(policy=PolicyPathConfig(path=tiny_policy_dir), detectors=["nope"])
    with pytest.raises(ValueError, match="`single_member_samples` must be 0 .member 0's own chunks. or >= 2"):
        BenchmarkOODConfig(policy=PolicyPathConfig(path=tiny_policy_dir), single_member_samples=1)


@pytest.mark.slow
def test_benchmark_ood_writes_table_numbers_figures_and_resumes(tiny_policy_dir, tmp_path, caplog, capsys):
    policy = tmp_path / "policy"
    shutil.copytree(tiny_policy_dir, policy)
    out = tmp_path / "bench"
    args = [
        "benchmark-ood",
        f"--policy.path={policy}",
        f"--output_dir={out}",
        "--fit_episodes=2",
        "--calibration_episodes=2",
        "--nominal_episodes=2",
        "--runs_per_scenario=1",
        "--alpha=0.4",
        "--single_member_samples=2",
        "--shifts=[dim_light@0.6,action_delay@1]",
        "--runs_per_shift=1",
        "--batch_envs=2",
    ]
    cli_main(args)
    result = json.loads((out / "detectors.json").read_text())
    assert list(result["detectors"]) == list(DETECTOR_NAMES)
    shifts = ["dim_light@0.6", "action_delay@1"]
    assert result["episodes"] == {
        "fit": 2,
        "calibration": 2,
        "nominal": 2,
        **dict.fromkeys(SCENARIOS, 1),
        **dict.fromkeys(shifts, 1),
    }
    for name, r in result["detectors"].items():
        assert "error" not in r, (name, r.get("error"))
        assert math.isfinite(r["threshold"]) and r["cost"]["ms_per_prediction"] > 0
        assert 0 < r["cost"]["ms_per_control_step"] < r["cost"]["ms_per_prediction"]
        assert r["false_alarms"]["episodes"] == 2
        assert set(r["scenarios"]) == set(SCENARIOS)
        for m in r["scenarios"].values():
            assert 0 <= m["auroc"] <= 1 and m["runs"] == 1
            assert {
                "tpr_at_threshold",
                "detection_delay_steps",
                "failure_prediction_balanced_accuracy",
            } <= set(m)
        assert list(r["shifts"]) == shifts
        for m in r["shifts"].values():
            assert m["runs"] == 1 and 0 <= m["success_rate"] <= 1
            flagged = [m["flagged_of_failures"], m["flagged_of_successes"]]
            assert sum(math.isnan(f) for f in flagged) == 1  # one run: it failed or it succeeded
        assert r["approach"]["in_approach"] <= r["approach"]["alarms"] <= 2
    # The table: the summary row of every detector, then one table per scenario with a row each.
    table = (out / "detectors.md").read_text()
    for scenario in SCENARIOS:
        assert f"## {scenario}" in table
    assert "## Shifts" in table and "## Where nominal alarms fall" in table
    rows = [
        line
        for line in table.splitlines()
        if line.startswith("| ") and not line.startswith(("| detector", "| shift"))
    ]
    # Summary, scenarios, balanced accuracy over shifts and alarm placement: a row per detector each; then
    # a row per shift.
    assert len(rows) == len(DETECTOR_NAMES) * (1 + len(SCENARIOS) + 2) + len(shifts)
    cost = float(rows[0].split(" | ")[4])
    assert cost == pytest.approx(
        result["detectors"][DETECTOR_NAMES[0]]["cost"]["ms_per_prediction"], abs=0.006
    )
    # One figure per detector, drawn (not one flat colour), with coloured traces.
    assert result["figures"] == {**{n: f"detector_{n}.png" for n in DETECTOR_NAMES}, "shifts": "shifts.png"}
    for name in [*DETECTOR_NAMES, "shifts"]:
        image = np.asarray(Image.open(out / result["figures"][name]).convert("RGB"), dtype=float)
        assert image.mean(axis=2).std() > 5, f"detector_{name}.png is blank"
        assert (image.max(axis=2) - image.min(axis=2) > 60).mean() > 0.001, f"no coloured trace in {name}"
    parts = sorted(p.name for p in (out / "parts").iterdir())
    assert parts == sorted(
        f"{n}.{ext}"
        for n in ("fit", "calibration", "nominal", *SCENARIOS, *shifts)
        for ext in ("json", "npz")
    )
    # The robustness report reads the benchmark: a row per shift, the gate's flags, the range status.
    cli_main(["robustness-report", f"--runs=[toy={out}]", f"--output_dir={tmp_path / 'robustness'}"])
    report = json.loads((tmp_path / "robustness" / "robustness.json").read_text())
    rows = report["policies"]["toy"]["shifts"]
    assert [r["shift"] for r in rows] == shifts and {r["range"] for r in rows} == {"untrained"}
    gate = result["detectors"]["ensemble_covariance"]["shifts"]
    for r in rows:
        assert r["success_rate"] == gate[r["shift"]]["success_rate"]
    assert (
        "| dim_light@0.6 | appearance | untrained |"
        in (tmp_path / "robustness" / "robustness.md").read_text()
    )
    with Image.open(tmp_path / "robustness" / "robustness.png") as figure:  # a plot, not an empty canvas
        assert min(figure.size) > 300 and len(figure.convert("RGB").getcolors(maxcolors=2**16) or ()) > 8
    # A second run rolls nothing out again: every part is reused, and the numbers are the same.
    caplog.set_level("INFO")
    cli_main(args[:-1] + ["--batch_envs=2", "--detectors=[ensemble_covariance,stac]"])
    assert sum("reusing" in r.getMessage() for r in caplog.records) == 9
    again = json.loads((out / "detectors.json").read_text())
    assert list(again["detectors"]) == ["ensemble_covariance", "stac"]
    for name in again["detectors"]:
        assert again["detectors"][name]["scenarios"] == result["detectors"][name]["scenarios"]
    assert {"beyond_failure_auroc", "beyond_most_failures_flagged_at_bar"} <= set(
        report["policies"]["toy"]["bars"]
    )
    # A report on a detector the benchmark no longer holds says which run and how to get it.
    with pytest.raises(SystemExit) as exc:
        cli_main(["robustness-report", f"--runs=[toy={out}]", "--detector=rnd", f"--output_dir={tmp_path}"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "Run 'toy'" in err and "benchmark-ood" in err
    # A policy retrained in place does not match the saved parts: they are run again.
    (policy / "model.safetensors").touch()
    caplog.clear()
    cli_main(args + ["--detectors=[epistemic]"])
    assert not any("reusing" in r.getMessage() for r in caplog.records)


def test_benchmark_asks_for_extra_chunks_when_members_draw_one(tiny_policy_dir, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        cli_main(["benchmark-ood", f"--policy.path={tiny_policy_dir}", f"--output_dir={tmp_path}"])
    assert exc.value.code == 2 and "--single_member_samples=8" in capsys.readouterr().err
    assert not (tmp_path / "parts").exists()  # refused before any rollout
