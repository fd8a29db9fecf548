"""The committed results re-render: every ``report.md`` under ``docs/results/`` is what ``render_report``
makes of the ``metrics.json`` beside it, so a change to the report's code that changes a committed
report shows here."""

import json
from pathlib import Path

import pytest

from lerobot_suture.experiments.report import render_report

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"
PAIRS = sorted(m for m in RESULTS.rglob("metrics.json") if (m.parent / "report.md").is_file())


def test_there_are_committed_reports():
    assert any(m.parent.name == "prior_servo_5500" for m in PAIRS)


@pytest.mark.parametrize("metrics", PAIRS, ids=lambda m: str(m.parent.relative_to(RESULTS)))
def test_a_committed_report_re_renders_identically(metrics):
    assert render_report(json.loads(metrics.read_text())) == (metrics.parent / "report.md").read_text()


def test_the_committed_episode_sample_covers_every_condition_and_a_change_shows():
    """``benchmarks/episode_outcomes.py``'s committed sample: each experiment's and each leaderboard cell's
    episodes, and its comparison names a changed outcome (what a refactor is checked against)."""
    import importlib.util
    import sys

    folder = RESULTS.parents[1] / "benchmarks"
    sys.path.insert(0, str(folder))
    try:
        spec = importlib.util.spec_from_file_location("episode_outcomes", folder / "episode_outcomes.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(folder))
    sample = json.loads((RESULTS / "benchmarks" / "episode_outcomes.json").read_text())["outcomes"]
    assert set(sample["episodes"]) == {
        "nominal",
        "needle_drop",
        "camera_moved",
        "phantom_servo",
        "phantom_moved_after_insertion",
    }
    assert set(sample["leaderboard"]) == set(module.LEADERBOARD_CONDITIONS)
    assert module.differences(sample, sample) == []
    changed = json.loads(json.dumps(sample))
    changed["episodes"]["nominal"][0]["success"] = not changed["episodes"]["nominal"][0]["success"]
    assert module.differences(changed, sample) == [
        f"/episodes/nominal[0]/success: {changed['episodes']['nominal'][0]['success']!r} != "
        f"{sample['episodes']['nominal'][0]['success']!r}"
    ]
