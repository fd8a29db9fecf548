"""``lerobot-suture score-study --policy.path=DIR``: the gate's uncertainty scores compared on validation seeds
(:mod:`lerobot_suture_studies.score_study`)."""

from __future__ import annotations

import draccus

from lerobot_suture_studies.benchmark_ood_report import fmt
from lerobot_suture_studies.score_study import ScoreStudyConfig, run_score_study


def main(argv: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=ScoreStudyConfig, args=argv, exit_on_error=False)
    result = run_score_study(cfg)
    best = result["choices"][0]
    own = next(r for r in result["choices"] if r["policy_own"])
    print(
        f"Best: {best['label']} (rank score {fmt(best['rank_score'])}); the policy's own {own['label']}: "
        f"{fmt(own['rank_score'])}. Table: {cfg.output_dir / 'score_study.md'}"
    )
