"""The paper's experiments with a trained ensemble, with numbers (``lerobot-suture experiments``).

With the gate in reporting mode (as the paper ran them) it rolls the policy out in

- experiment 1, needle dropped during execution (12 runs by default, as the paper);
- experiment 2, camera moved to an unseen viewpoint (8 runs);
- experiment 3.1, phantom moved during the approach (9 runs);
- experiment 3.2, phantom moved after insertion (27 runs);
- nominal episodes beside them (100 by default: success rate and false alarms);

then experiment 4, the CBF (the offline replay figure, and live runs of the policy and of an adversary
that pulls the needle sideways, with and without the filter), and finally the gate enforced with the
scripted surgeon taking over. It writes one figure per experiment, ``metrics.json``, ``report.md``
and ``traces.json`` into ``--output_dir``. ``traces.json`` holds the score and the alarm per step of
every episode run with the gate reporting (the nominal runs and experiments 1 to 3.2). Every episode's
seed is derived from ``--seed``, so a rerun gives the same numbers. The seeds are disjoint from the
recording seeds (0...) and the calibration seeds (the dataset's validation episodes, or 1,000,000...):
nothing here is tuned on them.
"""

from __future__ import annotations

import functools
import json
import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from lerobot_suture.experiments import metrics
from lerobot_suture.experiments.cbf_replay_figure import CBFReplayConfig, run_cbf_replay
from lerobot_suture.experiments.episode_metrics import (
    EXPERIMENTS,
    alarms,
    in_tissue_at_handover,
    ood_metrics,
    traces,
)
from lerobot_suture.experiments.plots import plot_uncertainty
from lerobot_suture.experiments.report import json_default, render_report
from lerobot_suture.experiments.sideways_pull import run_cbf_episode
from lerobot_suture.runtime.config import RolloutCommandConfig
from lerobot_suture.runtime.expert_rollout import run_expert_episode
from lerobot_suture.runtime.policy import GateMode, env_kwargs_for_policy, reporting_runner
from lerobot_suture.runtime.rollout import EpisodeLog, make_scenario_env, rollout_seeds
from lerobot_suture.runtime.seeds import episode_seeds
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.sim.task import ENTRY_TOLERANCE, EXIT_TOLERANCE

logger = logging.getLogger(__name__)

TRACES_FILE = "traces.json"


@dataclass
class ExperimentsConfig(RolloutCommandConfig):
    """Args (and those of :class:`~lerobot_suture.runtime.config.RolloutCommandConfig`; the policy is a
    trained and calibrated ensemble, ``lerobot-suture calibrate``):
    output_dir: where figures, ``metrics.json``, ``report.md`` and ``traces.json`` go.
    seed: base of every episode seed (test seeds: disjoint from recording and calibration).
    nominal_episodes: nominal runs (success rate with a 95% Wilson interval; false alarms).
    expert_episodes: nominal runs of the scripted expert, for its success rate beside the policy's.
    needle_drop_runs, camera_moved_runs, phantom_servo_runs, phantom_moved_after_insertion_runs: runs of
        experiments 1, 2, 3.1, 3.2 (the paper's counts by default).
    cbf_runs: runs of each arm of experiment 4 live (policy and adversary, filter on and off).
    enforced_runs: runs per scenario (nominal and the four perturbations) with the gate enforced and
        the scripted surgeon taking over.
    """

    output_dir: Path = Path("outputs/experiments")
    seed: int = 2_000_000
    nominal_episodes: int = 100
    expert_episodes: int = 100
    needle_drop_runs: int = 12
    camera_moved_runs: int = 8
    phantom_servo_runs: int = 9
    phantom_moved_after_insertion_runs: int = 27
    cbf_runs: int = 10
    enforced_runs: int = 5

    def __post_init__(self):
        super().__post_init__()
        counts = {k: v for k, v in asdict(self).items() if k.endswith(("_runs", "_episodes"))}
        bad = {k: v for k, v in counts.items() if v < 0}
        if bad:
            raise ValueError(f"Episode counts must be >= 0. Got {bad}.")
        if self.nominal_episodes < 1:
            raise ValueError(
                f"`nominal_episodes` must be >= 1 (false alarms need them). Got {self.nominal_episodes}."
            )

    def runs(self, scenario: str) -> int:
        return getattr(self, f"{scenario}_runs")


def _rollouts(
    cfg: ExperimentsConfig, runner, env_kwargs, scenario, seeds, desc, surgeon="none", cbf=None, trace=False
) -> list[EpisodeLog]:
    return rollout_seeds(
        functools.partial(make_scenario_env, env_kwargs, scenario, cbf, trace),
        runner,
        seeds,
        cfg.batch_envs,
        surgeon,
        desc,
        cfg.workers,
    )


def cbf_live(cfg: ExperimentsConfig, runner, env_kwargs: dict) -> dict:
    """Experiment 4 live: the policy (nominal) and the adversary, each with the filter on and off."""
    cbf_on, cbf_off = CBFConfig(enabled=True), CBFConfig(enabled=False)
    seeds = episode_seeds(cfg.seed, 40, cfg.cbf_runs)
    result = {}
    for name, cbf in (("filter_on", cbf_on), ("filter_off", cbf_off)):
        logs = _rollouts(
            cfg, runner, env_kwargs, "nominal", seeds, f"CBF live, policy, {name}", cbf=cbf, trace=True
        )
        active = [s for log in logs for s in log.steps if s.cbf_active]
        h_mins = [log.h_min_physics for log in logs if not math.isnan(log.h_min_physics)]
        result[f"policy_{name}"] = {
            "runs": len(logs),
            "violations": int(sum(h < 0 for h in h_mins)),
            "h_min": float(min(h_mins)) if h_mins else None,
            "intervention_rate": float(np.mean([s.cbf_intervened for s in active])) if active else 0.0,
            "tissue_strain_m": metrics.summarize([log.tissue_strain for log in logs]),
            "success_rate": float(np.mean([log.success for log in logs])),
        }
        adversary = [run_cbf_episode(s, cbf) for s in tqdm(seeds, desc=f"CBF live, adversary, {name}")]
        active_steps = sum(a.active_steps for a in adversary)
        result[f"adversary_{name}"] = {
            "runs": len(adversary),
            "violations": int(sum(a.h_min < 0 for a in adversary)),
            "h_min": float(min(a.h_min for a in adversary)) if adversary else None,
            "intervention_rate": sum(a.interventions for a in adversary) / active_steps
            if active_steps
            else 0.0,
            "tissue_strain_m": metrics.summarize([a.tissue_strain for a in adversary]),
        }
    return result


def enforced(cfg: ExperimentsConfig, runner, env_kwargs: dict) -> dict:
    """The gate enforced, the scripted surgeon taking over: autonomy, handovers, rescued insertions."""
    runner = runner.with_gate(GateMode.ENFORCE)
    out = {}
    for group, scenario in enumerate(["nominal"] + [s for _, s, _ in EXPERIMENTS]):
        logs = _rollouts(
            cfg,
            runner,
            env_kwargs,
            scenario,
            episode_seeds(cfg.seed, 50 + group, cfg.enforced_runs),
            f"enforced, {scenario}",
            "expert",
        )
        handed = [log for log in logs if log.handover_step is not None]
        out[scenario] = {
            "runs": len(logs),
            "autonomous_success_rate": float(np.mean([log.autonomous_success for log in logs]))
            if logs
            else math.nan,
            "handover_rate": len(handed) / len(logs) if logs else math.nan,
            "success_after_handover_rate": float(np.mean([log.success for log in handed]))
            if handed
            else None,
            # A surgeon cannot undo a needle already through the tissue at the wrong place.
            "handover_in_tissue_rate": float(np.mean([in_tissue_at_handover(log) for log in handed]))
            if handed
            else None,
            "handover_step": metrics.summarize([log.handover_step for log in handed]),
            "success_rate": float(np.mean([log.success for log in logs])) if logs else math.nan,
        }
    return out


def run_experiments(cfg: ExperimentsConfig) -> dict:
    """Run every experiment; writes the figures, ``metrics.json``, ``report.md`` and ``traces.json``."""
    started = time.perf_counter()
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    # The paper's experiments report the gate.
    runner = reporting_runner(cfg.policy.path, cfg.device, overrides=cfg.policy.overrides)
    policy = runner.policy
    if policy.ood_calibration is None:
        raise ValueError(
            f"The policy at {cfg.policy.path} has no O.O.D. calibration. Run `lerobot-suture calibrate "
            f"--policy.path={cfg.policy.path}` first."
        )
    env_kwargs = env_kwargs_for_policy(policy.config)
    threshold = policy.ood_calibration.threshold

    nominal = _rollouts(
        cfg, runner, env_kwargs, "nominal", episode_seeds(cfg.seed, 0, cfg.nominal_episodes), "nominal"
    )
    expert = [
        run_expert_episode(s)
        for s in tqdm(episode_seeds(cfg.seed, 1, cfg.expert_episodes), desc="expert, nominal")
    ]
    successes = sum(log.success for log in nominal)
    expert_successes = sum(e.success for e in expert)
    result: dict = {
        "policy_path": str(cfg.policy.path),
        "policy_overrides": cfg.policy.overrides,
        "calibration": policy.ood_calibration.to_dict(),
        "nominal": {
            "episodes": len(nominal),
            "success_rate": successes / len(nominal),
            "success_rate_wilson95": metrics.wilson_interval(successes, len(nominal)),
            "expert_episodes": len(expert),
            "expert_success_rate": expert_successes / len(expert) if expert else None,
            "expert_success_rate_wilson95": metrics.wilson_interval(expert_successes, len(expert)),
            "false_alarms": metrics.alarm_rates([alarms(log) for log in nominal]),
            # An alarm on a nominal run the policy is failing is not the same as one on a success.
            "false_alarms_by_outcome": {
                outcome: metrics.alarm_rates([alarms(log) for log in nominal if log.success == succeeded])
                for outcome, succeeded in (("successful", True), ("failed", False))
            },
            # Where the successful episodes peak: at the end of the task, or anywhere.
            "score_max_in_last_steps": {
                "end_steps": metrics.END_OF_TASK_STEPS,
                "share_of_successful_episodes": metrics.share_of_maxima_at_end(
                    [log.scores for log in nominal if log.success], metrics.END_OF_TASK_STEPS
                ),
            },
            "insertion": metrics.insertion_accuracy(
                [log.entry_error_m for log in nominal],
                [log.exit_error_m for log in nominal],
                ENTRY_TOLERANCE,
                EXIT_TOLERANCE,
            ),
        },
        "experiments": {},
        "figures": {},
    }
    nominal_scores = [log.scores for log in nominal]
    score_traces = {"threshold": threshold, "nominal": traces(nominal)}
    for group, (exp_id, scenario, title) in enumerate(EXPERIMENTS, start=2):
        runs = _rollouts(
            cfg, runner, env_kwargs, scenario, episode_seeds(cfg.seed, group, cfg.runs(scenario)), title
        )
        score_traces[scenario] = traces(runs)
        entry = ood_metrics(nominal, runs)
        entry["scenario"] = scenario
        result["experiments"][exp_id] = entry
        figure = plot_uncertainty(
            [log.scores for log in runs],
            threshold,
            cfg.output_dir / f"experiment_{exp_id.replace('.', '_')}_{scenario}.png",
            f"{title} ({len(runs)} runs)",
            onset_steps=[log.onset_step for log in runs],
            nominal_runs=nominal_scores[: max(1, min(len(nominal_scores), 20))],
            score_name=policy.config.uncertainty_score,
        )
        result["figures"][exp_id] = figure.name

    (cfg.output_dir / TRACES_FILE).write_text(json.dumps(score_traces, default=json_default))
    result["traces"] = TRACES_FILE
    replay = run_cbf_replay(CBFReplayConfig(output_dir=cfg.output_dir, seed=cfg.seed))
    result["cbf"] = {"offline_replay": replay, "live": cbf_live(cfg, runner, env_kwargs)}
    result["figures"]["4"] = "cbf_replay.png"
    result["gate_enforced"] = enforced(cfg, runner, env_kwargs)
    result["seconds"] = round(time.perf_counter() - started, 1)
    (cfg.output_dir / "metrics.json").write_text(
        json.dumps(result, separators=(",", ":"), default=json_default)
    )
    (cfg.output_dir / "report.md").write_text(render_report(result))
    return result
