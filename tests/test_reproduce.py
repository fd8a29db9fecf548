"""`lerobot-suture reproduce`: the comparison's tolerances, and the whole pipeline at toy scale, resumed."""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from lerobot_suture.experiments.compare import compare_metrics, comparison_markdown
from lerobot_suture.pipelines.reproduce import REFERENCE_RESULTS, STAGES

COMMITTED = json.loads((REFERENCE_RESULTS / "metrics.json").read_text())


def _verdicts(new: dict) -> dict[str, bool]:
    return {row.name: row.within for row in compare_metrics(COMMITTED, new)}


def test_the_committed_run_is_within_tolerance_of_itself():
    rows = compare_metrics(COMMITTED, COMMITTED)
    assert len(rows) >= 15 and all(row.within for row in rows)
    assert f"{len(rows)} of {len(rows)} rows within tolerance" in comparison_markdown(rows, "a", "b")


def test_each_tolerance_can_fail():
    new = copy.deepcopy(COMMITTED)
    new["nominal"]["success_rate"] = 0.80  # below the interval [0.902, 0.984] of 96 of 100
    new["experiments"]["3.2"]["auroc"] = COMMITTED["experiments"]["3.2"]["auroc"] - 0.06  # past the 0.05 band
    new["experiments"]["1"]["detection_delay_steps"]["median"] = 4.0  # 3 steps later than 1
    new["cbf"]["live"]["policy_filter_on"]["violations"] = 1  # the filter's guarantee is not statistical
    del new["experiments"]["2"]  # a figure the new run lacks is not within
    verdicts = _verdicts(new)
    failed = {name for name, within in verdicts.items() if not within}
    assert failed == {
        "nominal success, policy",
        "3.2 phantom moved after insertion: AUROC",
        "1 needle drop: detection delay, median",
        "CBF policy filter on: violations",
        "2 camera moved: AUROC",
        "2 camera moved: flagged (TPR at threshold)",
        "2 camera moved: detection delay, median",
    }
    assert "**no**" in comparison_markdown(compare_metrics(COMMITTED, new), "a", "b")


def test_an_undefined_delay_agrees_only_with_an_undefined_one():
    assert COMMITTED["experiments"]["3.1"]["detection_delay_steps"]["median"] is None  # servo: never flagged
    new = copy.deepcopy(COMMITTED)
    assert _verdicts(new)["3.1 phantom servo: detection delay, median"]
    new["experiments"]["3.1"]["detection_delay_steps"]["median"] = 5.0
    assert not _verdicts(new)["3.1 phantom servo: detection delay, median"]


def _reproduce(out: Path) -> str:
    result = subprocess.run(
        [
            str(Path(sys.executable).parent / "lerobot-suture"),
            "reproduce",
            "--toy=true",
            f"--output_dir={out}",
        ],
        env={**os.environ, "HF_HUB_OFFLINE": "1"},
        capture_output=True,
        text=True,
        timeout=1200,
    )
    log = result.stdout + result.stderr
    assert result.returncode == 0, log[-6000:]
    return log


@pytest.mark.slow
def test_the_pipeline_at_toy_scale_runs_and_a_rerun_redoes_nothing(tmp_path):
    out = tmp_path / "reproduce"
    log = _reproduce(out)
    assert "# Reproduction (toy scale)" in log and "rows within tolerance" in log
    comparison = json.loads((out / "comparison.json").read_text())
    assert comparison["toy"] and len(comparison["rows"]) == len(compare_metrics(COMMITTED, COMMITTED))
    # Every rate, AUROC and count has a value; a delay is undefined when no run was flagged.
    assert all(row["new"] is not None for row in comparison["rows"] if "delay" not in row["name"])
    first = json.loads((out / "timings.json").read_text())
    assert set(first) == set(STAGES) and all(seconds > 0 for seconds in first.values())
    metrics = json.loads((out / "experiments" / "metrics.json").read_text())
    assert metrics["nominal"]["episodes"] == 2

    log = _reproduce(out)  # everything is there: each stage finds its result and keeps it
    assert "already trained" in log and "already calibrated" in log and "experiments already run" in log
    second = json.loads((out / "timings.json").read_text())
    assert second["train"] - first["train"] < 5 and second["experiments"] - first["experiments"] < 5
    assert json.loads((out / "experiments" / "metrics.json").read_text()) == metrics
