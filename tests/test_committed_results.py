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
