"""`lerobot-suture experiments` end to end at toy scale on a tiny (untrained) calibrated ensemble."""

import json
import math
import shutil

import numpy as np
from PIL import Image

from lerobot_suture.cli import main as cli_main
from lerobot_suture.experiments.episode_metrics import in_tissue_at_handover
from lerobot_suture.runtime.rollout import EpisodeLog, StepLog
from lerobot_suture.safety.ood.calibration import fit_calibration
from lerobot_suture.safety.ood.calibration_file import save_calibration


def _step(in_tissue: bool) -> StepLog:
    return StepLog(0.0, 1.0, False, False, False, "policy", False, in_tissue)


def test_needle_in_tissue_at_handover_is_read_before_the_surgeon_acts():
    log = EpisodeLog(seed=0, scenario="nominal", steps=[_step(False), _step(True), _step(True)])
    log.handover_step = 1  # released after step 0: the needle was not in yet
    assert not in_tissue_at_handover(log)
    log.handover_step = 2
    assert in_tissue_at_handover(log)
    log.handover_step = 0  # released before any step: the episode's start, needle outside
    assert not in_tissue_at_handover(log)


def test_experiments_write_figures_metrics_and_report(tiny_policy_dir, tmp_path):
    """The paper's results command at toy scale (an untrained tiny ensemble, one run per experiment): every
    file it writes, and what is in each."""
    policy = tmp_path / "policy"
    shutil.copytree(tiny_policy_dir, policy)
    rng = np.random.default_rng(0)
    save_calibration(fit_calibration(np.abs(rng.lognormal(-3, 0.3, 100)), model="lognormal"), policy)
    out = tmp_path / "experiments"
    cli_main(
        [
            "experiments",
            f"--policy.path={policy}",
            f"--output_dir={out}",
            "--nominal_episodes=2",
            "--expert_episodes=2",
            "--needle_drop_runs=1",
            "--camera_moved_runs=1",
            "--phantom_servo_runs=1",
            "--phantom_moved_after_insertion_runs=1",
            "--cbf_runs=1",
            "--enforced_runs=1",
        ]
    )
    result = json.loads((out / "metrics.json").read_text())
    assert set(result["experiments"]) == {"1", "2", "3.1", "3.2"}
    assert result["nominal"]["expert_success_rate"] == 1.0
    assert result["cbf"]["live"]["adversary_filter_on"]["violations"] == 0
    assert result["cbf"]["live"]["adversary_filter_off"]["violations"] == 1
    assert result["cbf"]["live"]["policy_filter_on"]["violations"] == 0
    assert set(result["gate_enforced"]) == {
        "nominal",
        "needle_drop",
        "camera_moved",
        "phantom_servo",
        "phantom_moved_after_insertion",
    }
    assert result["nominal"]["insertion"]["episodes"] == 2
    by_outcome = result["nominal"]["false_alarms_by_outcome"]
    assert by_outcome["successful"]["episodes"] + by_outcome["failed"]["episodes"] == 2
    alarmed = by_outcome["successful"]["alarmed_episodes"] + by_outcome["failed"]["alarmed_episodes"]
    assert alarmed == result["nominal"]["false_alarms"]["alarmed_episodes"]
    assert by_outcome["successful"]["episodes"] == round(result["nominal"]["success_rate"] * 2)
    end = result["nominal"]["score_max_in_last_steps"]
    assert end["end_steps"] == 8
    if by_outcome["successful"]["episodes"]:
        assert 0.0 <= end["share_of_successful_episodes"] <= 1.0
    else:
        assert math.isnan(end["share_of_successful_episodes"])
    for entry in result["experiments"].values():
        assert 0.0 <= entry["auroc_common_steps"] <= 1.0
        assert entry["flagged_runs"] == round(entry["tpr_at_threshold"] * entry["runs"])
        low, high = entry["tpr_wilson95"]
        assert low <= entry["tpr_at_threshold"] <= high
        assert all(math.isnan(x) for x in entry["auroc_interval95"])  # DeLong needs two runs a side
    traces = json.loads((out / result["traces"]).read_text())
    assert len(traces["nominal"]) == 2 and len(traces["needle_drop"]) == 1
    drop = traces["needle_drop"][0]
    assert len(drop["scores"]) == len(drop["alarms"]) > drop["onset_step"] >= 0
    assert traces["threshold"] == result["calibration"]["threshold"]
    for entry in result["gate_enforced"].values():
        assert entry["handover_step"]["n"] == round(entry["handover_rate"] * entry["runs"])
        if entry["handover_rate"] == 0:
            assert entry["handover_in_tissue_rate"] is None
        else:
            assert 0.0 <= entry["handover_in_tissue_rate"] <= 1.0
    report = (out / "report.md").read_text()
    assert "| 1 | needle_drop | 1 |" in report
    drop_row = next(line for line in report.splitlines() if line.startswith("| 1 | needle_drop |"))
    auroc_cell, tpr_cell = drop_row.split("|")[4], drop_row.split("|")[6]
    assert "[" not in auroc_cell and " [" in tpr_cell  # no AUROC interval of one run; Wilson's of the TPR
    assert "Where the needle crossed the tissue" in report
    assert "(alarmed episodes: " in report
    assert "in their last 8 control steps" in report or "No nominal episode succeeded" in report
    assert "AUROC over common steps" in report and "needle in tissue at handover" in report
    for name in result["figures"].values():
        image = np.asarray(Image.open(out / name).convert("L"), dtype=float)
        assert image.std() > 5, f"{name} is blank"
    assert "![experiment 3.2](experiment_3_2_phantom_moved_after_insertion.png)" in report
    replay = json.loads((out / "cbf_replay.json").read_text())
    assert replay == result["cbf"]["offline_replay"]
    assert replay["left_set_reference"] and not replay["left_set_safe"] and replay["h_min_safe"] >= 0
    # Nothing else is written, and nothing is missing.
    written = {p.name for p in out.iterdir()}
    assert written == {
        *result["figures"].values(),
        "metrics.json",
        "report.md",
        "traces.json",
        "cbf_replay.json",
    }
