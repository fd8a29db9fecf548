"""``lerobot-suture score-study``: which uncertainty score separates the perturbations best, on validation seeds.

The gate reads one number per prediction, and the ensemble's config chooses how it is computed from the
members' samples: the score (``uncertainty_score``), the action space (``uncertainty_space``), the
covariance (``uncertainty_source``) and the predicted steps (``uncertainty_steps``). This study rolls the
policy out once, nominal and in each perturbation scenario, on seeds kept apart from the experiments'
test seeds, and scores every prediction in every way the policy can (:meth:`rescore`, the same samples).
Per choice it fits the per-episode threshold on the nominal runs (as ``calibrate`` does) and reports
what ``experiments`` reports per scenario: episode AUROC, AUROC over the steps both episodes lasted,
true-positive rate and detection delay at that threshold. It writes ``score_study.json``,
``score_study.md`` (a table, best first) and ``score_study.png`` (AUROC per choice and scenario).

Choose on these numbers, then calibrate for the choice (``lerobot-suture calibrate --policy.path=DIR
--uncertainty_steps=action``, which writes it into the policy's ``config.json``) and run the experiments
on the test seeds. The seeds here
(1,500,000...) are disjoint from the recording (0...), calibration (1,000,000...) and test
(2,000,000...) seeds, so choosing here does not tune on the test seeds.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from lerobot_suture.experiments.episode_metrics import EXPERIMENTS, ood_metrics
from lerobot_suture.experiments.metrics import END_OF_TASK_STEPS, share_of_maxima_at_end
from lerobot_suture.experiments.report import json_default
from lerobot_suture.plotting import save_figure
from lerobot_suture.runtime.config import RolloutCommandConfig
from lerobot_suture.runtime.policy import GateMode, env_kwargs_for_policy, reporting_runner
from lerobot_suture.runtime.rollout import EpisodeLog, make_scenario_env, rollout_seeds
from lerobot_suture.runtime.seeds import episode_seeds
from lerobot_suture.safety.ood.calibration import default_model, fit_calibration, min_calibration_episodes
from lerobot_suture.safety.ood.gate import OODGate
from lerobot_suture_studies.benchmark_ood_report import fmt

logger = logging.getLogger(__name__)


@dataclass
class ScoreStudyConfig(RolloutCommandConfig):
    """Args (and those of :class:`~lerobot_suture.runtime.config.RolloutCommandConfig`; the policy is a
    trained ensemble, no calibration needed):
    output_dir: where ``score_study.json``, ``score_study.md`` and ``score_study.png`` go.
    seed: base of every episode seed (validation seeds, disjoint from recording, calibration and test).
    nominal_episodes: nominal runs the per-episode threshold of each choice is fitted on.
    runs_per_scenario: runs of each perturbation scenario (experiments 1, 2, 3.1, 3.2).
    alpha: per-episode false-alarm rate the thresholds are fitted for.
    """

    output_dir: Path = Path("outputs/score_study")
    seed: int = 1_500_000
    nominal_episodes: int = 40
    runs_per_scenario: int = 12
    alpha: float = 0.05

    def __post_init__(self):
        super().__post_init__()
        if self.workers != 1:
            raise ValueError(
                f"`workers` must be 1 here (the study scores every prediction in this process). Got {self.workers}."
            )
        if self.runs_per_scenario < 1:
            raise ValueError(f"`runs_per_scenario` must be >= 1. Got {self.runs_per_scenario}.")
        needed = min_calibration_episodes(self.alpha)
        if self.nominal_episodes < needed:
            raise ValueError(
                f"A per-episode threshold at alpha={self.alpha} needs at least {needed} nominal episodes. "
                f"Got `nominal_episodes`={self.nominal_episodes}; raise it or raise `--alpha`."
            )


def choice_grid(policy) -> list[dict[str, str]]:
    """Every distinct choice of score the policy can make (config field -> value), its own first."""
    choices = policy.config.score_choices()
    if not policy.has_action_stats:  # dataset units need the action statistics
        choices["uncertainty_space"] = ("normalized",)
    own = {name: getattr(policy.config, name) for name in choices}
    grid = [dict(zip(choices, values, strict=True)) for values in itertools.product(*choices.values())]
    return [own] + [c for c in grid if c != own]


def choice_label(choice: dict[str, str]) -> str:
    """A short name of a score choice, e.g. ``max_abs_cov/normalized/total/horizon`` (its values in order)."""
    return "/".join(choice.values())


class RescoringRunner:
    """Wraps a :class:`~lerobot_suture.runtime.policy.PolicyRunner` (for the rollout functions) and scores
    each new prediction in every way of ``choices``. Per control step it keeps the latest prediction's
    scores (as the gate holds its score between predictions); :meth:`take` hands them out per episode.
    """

    def __init__(self, runner, choices: list[dict[str, str]]):
        if runner.gate is not GateMode.REPORT:
            # An enforced gate stops asking the policy, and the steps would no longer match the calls.
            raise ValueError(
                "The score study runs the gate in reporting mode: pass a GateMode.REPORT runner."
            )
        self.runner, self.choices = runner, choices
        self.policy = runner.policy
        self._calls: list[np.ndarray] = []  # per act_batch call: (B, C)
        self.batches: list[np.ndarray] = []  # per rollout batch: (calls, B, C)

    def reset(self, seeds=None) -> None:
        self._close_batch()
        self.runner.reset(seeds=seeds)

    def act_batch(self, observations: list[dict], tasks=None) -> np.ndarray:
        actions = self.runner.act_batch(observations, tasks)
        if self.policy.ood_status(0)["new_prediction"]:
            prediction = self.policy.last_prediction
            scores = [self.policy.rescore(prediction, **c).float().cpu().numpy() for c in self.choices]
            self._calls.append(np.stack(scores, axis=1))
        else:
            self._calls.append(self._calls[-1])
        return actions

    def _close_batch(self) -> None:
        if self._calls:
            self.batches.append(np.stack(self._calls))
        self._calls = []

    def take(self, logs: list[EpisodeLog]) -> list[np.ndarray]:
        """Per episode of ``logs`` (the rollouts since the last ``take``, in order): (steps, C) scores.

        Each rollout batch (one ``reset``) holds one row per env; an episode that ended early keeps its
        row, and its steps are the first ``len(log.steps)`` calls.
        """
        self._close_batch()
        batches, self.batches = self.batches, []
        rows = [(b, r) for b, batch in enumerate(batches) for r in range(batch.shape[1])]
        if len(rows) != len(logs):
            raise ValueError(f"{len(logs)} episodes were logged but {len(rows)} were scored.")
        out = []
        for log, (b, r) in zip(logs, rows, strict=True):
            if batches[b].shape[0] < len(log.steps):
                raise ValueError(
                    f"Episode {log.seed} has {len(log.steps)} steps but {batches[b].shape[0]} scored calls."
                )
            out.append(batches[b][: len(log.steps), r])
        return out


def with_scores(log: EpisodeLog, scores: np.ndarray, gate: OODGate) -> EpisodeLog:
    """``log`` with its scores replaced by ``scores`` (one per step) and its alarms replayed through
    ``gate`` (updated at each new prediction, as the policy's own gate is)."""
    gate.reset()
    steps = []
    for step, score in zip(log.steps, scores, strict=True):
        if step.new_prediction:
            gate.update(float(score))
        steps.append(replace(step, score=float(score), ood=gate.decision, threshold=gate.threshold))
    return replace(log, steps=steps)


def evaluate_choice(
    nominal: list[EpisodeLog],
    nominal_scores: list[np.ndarray],
    scenarios: dict[str, tuple[list[EpisodeLog], list[np.ndarray]]],
    alpha: float,
    model: str = "lognormal",
) -> dict:
    """One score choice's numbers: its per-episode threshold fitted on ``nominal`` and, per scenario,
    the experiments' O.O.D. metrics (:func:`~lerobot_suture.experiments.paper.ood_metrics`).

    ``model``: the calibration's I.D. model, ``normal`` for scores that can be negative (``logdet``).
    """
    predictions = [
        (score, episode)
        for episode, (log, scores) in enumerate(zip(nominal, nominal_scores, strict=True))
        for step, score in zip(log.steps, scores, strict=True)
        if step.new_prediction
    ]
    values, ids = (np.asarray(x) for x in zip(*predictions, strict=True))
    calibration = fit_calibration(values, model=model, alpha=alpha, mode="per_episode", episode_ids=ids)
    gate = OODGate(calibration)
    nominal_v = [with_scores(log, s, gate) for log, s in zip(nominal, nominal_scores, strict=True)]
    result = {
        "threshold": calibration.threshold,
        "false_alarm_per_episode_in_sample": float(
            np.mean([any(s.ood for s in log.steps) for log in nominal_v])
        ),
        "nominal_max_in_last_steps": share_of_maxima_at_end(
            [log.scores for log in nominal_v if log.success], END_OF_TASK_STEPS
        ),
        "scenarios": {},
    }
    for scenario, (logs, scores) in scenarios.items():
        runs = [with_scores(log, s, gate) for log, s in zip(logs, scores, strict=True)]
        result["scenarios"][scenario] = ood_metrics(nominal_v, runs)
    result["mean_auroc"] = _mean([m["auroc"] for m in result["scenarios"].values()])
    result["mean_auroc_common_steps"] = _mean([m["auroc_common_steps"] for m in result["scenarios"].values()])
    result["rank_score"] = _mean([result["mean_auroc"], result["mean_auroc_common_steps"]])
    return result


def run_score_study(cfg: ScoreStudyConfig) -> dict:
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    base = reporting_runner(
        cfg.policy.path,
        cfg.device,
        needs="rescore",
        needed_for="the score study needs an ensemble_diffusion policy, which can score a prediction in "
        "several ways.",
        overrides=cfg.policy.overrides,
    )
    choices = choice_grid(base.policy)
    runner = RescoringRunner(base, choices)
    env_kwargs = env_kwargs_for_policy(base.policy.config)

    def rollouts(group: int, scenario: str, n: int, desc: str) -> tuple[list[EpisodeLog], list[np.ndarray]]:
        seeds = episode_seeds(cfg.seed, group, n)
        logs = rollout_seeds(
            lambda: make_scenario_env(env_kwargs, scenario), runner, seeds, cfg.batch_envs, desc=desc
        )
        return logs, runner.take(logs)

    nominal, nominal_scores = rollouts(0, "nominal", cfg.nominal_episodes, "nominal (validation seeds)")
    scenarios = {
        scenario: rollouts(group, scenario, cfg.runs_per_scenario, title)
        for group, (_, scenario, title) in enumerate(EXPERIMENTS, start=2)
    }
    per_choice = []
    for c, choice in enumerate(choices):
        try:
            numbers = evaluate_choice(
                nominal,
                [s[:, c] for s in nominal_scores],
                {name: (logs, [s[:, c] for s in scores]) for name, (logs, scores) in scenarios.items()},
                cfg.alpha,
                model=default_model(choice["uncertainty_score"]),
            )
        except ValueError as exc:  # one choice's calibration failing costs that row, not the rollouts
            logger.warning("Score choice %s: %s", choice_label(choice), exc)
            numbers = {"error": str(exc), "rank_score": math.nan, "scenarios": {}}
        per_choice.append({"choice": choice, "label": choice_label(choice), "policy_own": c == 0, **numbers})
    result = {
        "policy_path": str(cfg.policy.path),
        "seed": cfg.seed,
        "alpha": cfg.alpha,
        "nominal_episodes": len(nominal),
        "nominal_success_rate": float(np.mean([log.success for log in nominal])),
        "runs_per_scenario": cfg.runs_per_scenario,
        # Episode AUROC alone rewards a score that grows once a failed run goes on past where nominal
        # episodes end; the AUROC over common steps asks what the score says while both are under way.
        "ranked_by": "mean of the mean episode AUROC and the mean AUROC over common steps",
        "choices": sorted(per_choice, key=lambda r: -_nan_low(r["rank_score"])),
    }
    (cfg.output_dir / "score_study.json").write_text(
        json.dumps(result, separators=(",", ":"), default=json_default)
    )
    (cfg.output_dir / "score_study.md").write_text(render_table(result))
    plot_score_study(result, cfg.output_dir / "score_study.png")
    return result


def _mean(values: list[float]) -> float:
    finite = [v for v in values if v is not None and not math.isnan(v)]
    return float(np.mean(finite)) if finite else math.nan


def _nan_low(x: float) -> float:
    return -math.inf if x is None or math.isnan(x) else x


def render_table(result: dict) -> str:
    """``score_study.md``: one row per score choice, best rank score first."""
    scenarios = [s for _, s, _ in EXPERIMENTS]
    head = (
        ["score / space / source / steps", "rank score", "mean AUROC (common steps)"]
        + [f"AUROC {s} (common steps)" for s in scenarios]
        + ["needle-drop delay", f"nominal max in last {END_OF_TASK_STEPS} steps"]
    )
    lines = [
        f"# Score study: {result['policy_path']}",
        "",
        f"Validation seeds from {result['seed']}: {result['nominal_episodes']} nominal episodes (policy "
        f"success {result['nominal_success_rate']:.0%}) and {result['runs_per_scenario']} runs per scenario. "
        f"Each choice's per-episode threshold is fitted on the nominal episodes at alpha = {result['alpha']}. "
        "Rank score: the mean of the mean episode AUROC and the mean AUROC over the steps both episodes "
        "lasted (episode AUROC alone rewards a score that grows once a failed run goes on past where "
        "nominal episodes end). The policy's own choice is in bold.",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    for row in result["choices"]:
        label = f"**{row['label']}**" if row["policy_own"] else row["label"]
        if "error" in row:
            lines.append(f"| {label} | failed: {row['error']} |" + " |" * (len(head) - 2))
            continue
        cells = [
            label,
            fmt(row["rank_score"]),
            f"{fmt(row['mean_auroc'])} ({fmt(row['mean_auroc_common_steps'])})",
        ]
        for s in scenarios:
            m = row["scenarios"][s]
            cells.append(f"{fmt(m['auroc'])} ({fmt(m['auroc_common_steps'])})")
        delay = row["scenarios"]["needle_drop"]["detection_delay_steps"]
        cells.append(f"{delay['median']} ({delay['n']} detected)" if delay["n"] else "none detected")
        cells.append(fmt(row["nominal_max_in_last_steps"]))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot_score_study(result: dict, path: Path) -> Path:
    """AUROC per score choice (rows) and scenario (columns) as two heatmaps, per episode and over the
    steps both episodes lasted; the policy's own choice is marked with an asterisk."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenarios = [s for _, s, _ in EXPERIMENTS]
    rows = result["choices"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 0.28 * len(rows) + 1.8), sharey=True)
    for ax, key, title in (
        (axes[0], "auroc", "episode AUROC"),
        (axes[1], "auroc_common_steps", "AUROC over the steps both episodes lasted"),
    ):
        values = np.array(
            [[r["scenarios"][s][key] if s in r["scenarios"] else math.nan for s in scenarios] for r in rows],
            dtype=float,
        )
        image = ax.imshow(values, cmap="RdYlGn", vmin=0.0, vmax=1.0, aspect="auto")
        ax.set_xticks(range(len(scenarios)), [s.replace("_", "\n") for s in scenarios], fontsize=8)
        for i, j in itertools.product(range(values.shape[0]), range(values.shape[1])):
            if not math.isnan(values[i, j]):
                ax.text(j, i, f"{values[i, j]:.2f}", ha="center", va="center", fontsize=6)
        ax.set_title(title, fontsize=9)
    axes[0].set_yticks(
        range(len(rows)), [("* " if r["policy_own"] else "") + r["label"] for r in rows], fontsize=7
    )
    fig.colorbar(image, ax=axes, label="AUROC against nominal episodes", shrink=0.8)
    fig.suptitle("Score choices on validation seeds (* the policy's own), best rank score first", fontsize=9)
    save_figure(fig, path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path
