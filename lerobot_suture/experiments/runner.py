"""``lerobot-suture experiments``: the paper's experiments with a trained ensemble, with numbers.

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

import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import draccus
import numpy as np
from tqdm import tqdm

from lerobot_suture.calibrate import PolicyPathConfig
from lerobot_suture.experiments import metrics
from lerobot_suture.experiments.adversary import run_cbf_episode
from lerobot_suture.experiments.plots import plot_uncertainty
from lerobot_suture.rollout import EpisodeLog, make_scenario_env, rollout_seeds
from lerobot_suture.rollout_expert import run_expert_episode
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.sim.task import ENTRY_TOLERANCE, EXIT_TOLERANCE

logger = logging.getLogger(__name__)

# (id, scenario, title) of the paper's O.O.D. experiments.
EXPERIMENTS = (
    ("1", "needle_drop", "Experiment 1: needle dropped during execution"),
    ("2", "camera_moved", "Experiment 2: camera moved to an unseen viewpoint"),
    ("3.1", "phantom_servo", "Experiment 3.1: phantom moved during the approach"),
    ("3.2", "phantom_moved_after_insertion", "Experiment 3.2: phantom moved after insertion"),
)
_SEED_STRIDE = 10_000  # seeds of different groups never overlap
TRACES_FILE = "traces.json"


@dataclass
class ExperimentsConfig:
    """Args:
    policy: ``--policy.path=DIR``, a trained and calibrated ensemble (``lerobot-suture calibrate``).
    output_dir: where figures, ``metrics.json``, ``report.md`` and ``traces.json`` go.
    seed: base of every episode seed (test seeds: disjoint from recording and calibration).
    nominal_episodes: nominal runs (success rate with a 95% Wilson interval; false alarms).
    expert_episodes: nominal runs of the scripted expert, for its success rate beside the policy's.
    needle_drop_runs, camera_moved_runs, phantom_servo_runs, phantom_moved_after_insertion_runs: runs of
        experiments 1, 2, 3.1, 3.2 (the paper's counts by default).
    cbf_runs: runs of each arm of experiment 4 live (policy and adversary, filter on and off).
    enforced_runs: runs per scenario (nominal and the four perturbations) with the gate enforced and
        the scripted surgeon taking over.
    batch_envs: envs run in lockstep with one batched policy call per step (same seeds and batch_envs:
        same numbers).
    device: torch device of the policy.
    """

    policy: PolicyPathConfig = field(default_factory=PolicyPathConfig)
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
    batch_envs: int = 8
    device: str = "cpu"

    def __post_init__(self):
        if self.policy.path is None:
            raise ValueError("`--policy.path` is required: a trained, calibrated ensemble directory.")
        counts = {k: v for k, v in asdict(self).items() if k.endswith(("_runs", "_episodes"))}
        if self.batch_envs < 1:
            raise ValueError(f"`batch_envs` must be >= 1. Got {self.batch_envs}.")
        bad = {k: v for k, v in counts.items() if v < 0}
        if bad:
            raise ValueError(f"Episode counts must be >= 0. Got {bad}.")
        if self.nominal_episodes < 1:
            raise ValueError(
                f"`nominal_episodes` must be >= 1 (false alarms need them). Got {self.nominal_episodes}."
            )

    def runs(self, scenario: str) -> int:
        return getattr(self, f"{scenario}_runs")


def episode_seeds(base: int, group: int, n: int) -> list[int]:
    """The seeds of ``n`` episodes of one group (a scenario, an arm) under the base seed ``base``."""
    return [base + group * _SEED_STRIDE + k for k in range(n)]


def _rollouts(
    cfg: ExperimentsConfig, runner, env_kwargs, scenario, seeds, desc, surgeon="none", cbf=None, trace=False
) -> list[EpisodeLog]:
    return rollout_seeds(
        lambda: make_scenario_env(env_kwargs, scenario, cbf, trace),
        runner,
        seeds,
        cfg.batch_envs,
        surgeon,
        desc,
    )


def _traces(logs: list[EpisodeLog]) -> list[dict]:
    """Per episode, what the figures and the O.O.D. metrics are computed from: the score and the
    gate's alarm at every control step, the onset and the outcome (``traces.json``).
    """
    return [
        {
            "seed": log.seed,
            "success": log.success,
            "onset_step": log.onset_step,
            "scores": [float(f"{x:.6g}") for x in log.scores],
            "alarms": [int(a) for a in _alarms(log)],
        }
        for log in logs
    ]


def _in_tissue_at_handover(log: EpisodeLog) -> bool:
    """Whether the needle was in tissue when the gate released control (before the surgeon acted)."""
    step = log.handover_step
    return bool(step) and log.steps[step - 1].needle_in_tissue  # no step before: the episode's start


def _alarms(log: EpisodeLog) -> list[bool]:
    return [s.ood for s in log.steps]


def ood_metrics(nominal: list[EpisodeLog], runs: list[EpisodeLog]) -> dict:
    """Episode-level AUROC against nominal runs and TPR at the calibrated threshold, each with its 95%
    interval (DeLong; Wilson), and the detection delay."""
    onsets = [log.onset_step for log in runs]
    flagged = [
        onset is not None and metrics.first_alarm_after(_alarms(log), onset) is not None
        for log, onset in zip(runs, onsets, strict=True)
    ]
    delays = metrics.detection_delays(
        [(_alarms(log), onset) for log, onset in zip(runs, onsets, strict=True)]
    )
    nominal_maxima = [metrics.episode_score(log.scores) for log in nominal]
    run_maxima = [metrics.episode_score(log.scores) for log in runs]
    n_flagged = sum(flagged)
    return {
        "runs": len(runs),
        "auroc": metrics.auroc(nominal_maxima, run_maxima),
        "auroc_interval95": metrics.auroc_interval(nominal_maxima, run_maxima),
        "auroc_common_steps": metrics.auroc_over_common_steps(
            [log.scores for log in nominal], [log.scores for log in runs], onsets
        ),
        "tpr_at_threshold": n_flagged / len(runs) if runs else math.nan,
        "flagged_runs": n_flagged,
        "tpr_wilson95": metrics.wilson_interval(n_flagged, len(runs)),
        "detection_delay_steps": metrics.summarize(delays),
        "onset_step": metrics.summarize([o for o in onsets if o is not None]),
        "policy_success_rate": float(np.mean([log.success for log in runs])) if runs else math.nan,
    }


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
    runner.policy.config.ood.enforce = True
    try:
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
                "handover_in_tissue_rate": float(np.mean([_in_tissue_at_handover(log) for log in handed]))
                if handed
                else None,
                "handover_step": metrics.summarize([log.handover_step for log in handed]),
                "success_rate": float(np.mean([log.success for log in logs])) if logs else math.nan,
            }
        return out
    finally:
        runner.policy.config.ood.enforce = False


def run_experiments(cfg: ExperimentsConfig) -> dict:
    from lerobot_suture.experiments.cbf_offline import CBFReplayConfig, run_cbf_replay
    from lerobot_suture.policy_runner import env_kwargs_for_policy, reporting_runner

    started = time.perf_counter()
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    runner = reporting_runner(cfg.policy.path, cfg.device)  # the paper's experiments report the gate
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
        "calibration": policy.ood_calibration.to_dict(),
        "nominal": {
            "episodes": len(nominal),
            "success_rate": successes / len(nominal),
            "success_rate_wilson95": metrics.wilson_interval(successes, len(nominal)),
            "expert_episodes": len(expert),
            "expert_success_rate": expert_successes / len(expert) if expert else None,
            "expert_success_rate_wilson95": metrics.wilson_interval(expert_successes, len(expert)),
            "false_alarms": metrics.alarm_rates([_alarms(log) for log in nominal]),
            # An alarm on a nominal run the policy is failing is not the same as one on a success.
            "false_alarms_by_outcome": {
                outcome: metrics.alarm_rates([_alarms(log) for log in nominal if log.success == succeeded])
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
    traces = {"threshold": threshold, "nominal": _traces(nominal)}
    for group, (exp_id, scenario, title) in enumerate(EXPERIMENTS, start=2):
        runs = _rollouts(
            cfg, runner, env_kwargs, scenario, episode_seeds(cfg.seed, group, cfg.runs(scenario)), title
        )
        traces[scenario] = _traces(runs)
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

    (cfg.output_dir / TRACES_FILE).write_text(json.dumps(traces, default=json_default))
    result["traces"] = TRACES_FILE
    replay = run_cbf_replay(CBFReplayConfig(output_dir=cfg.output_dir, seed=cfg.seed))
    result["cbf"] = {"offline_replay": replay, "live": cbf_live(cfg, runner, env_kwargs)}
    result["figures"]["4"] = "cbf_replay.png"
    result["gate_enforced"] = enforced(cfg, runner, env_kwargs)
    result["seconds"] = round(time.perf_counter() - started, 1)
    (cfg.output_dir / "metrics.json").write_text(json.dumps(result, indent=2, default=json_default))
    (cfg.output_dir / "report.md").write_text(render_report(result))
    return result


def json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serializable: {type(value).__name__}")


def _fmt(value, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return str(value)


def _interval(bounds) -> str:
    """`` [low, high]`` after a figure; nothing where there is none (one run a side, or older results)."""
    if bounds is None or any(b is None or math.isnan(b) for b in bounds):
        return ""
    return f" [{_fmt(bounds[0])}, {_fmt(bounds[1])}]"


def _settings_note(calibration: dict) -> str:
    settings = calibration.get("score_settings") or {}
    if "uncertainty_samples_per_member" not in settings:
        return ""
    return (
        f", {settings['uncertainty_source']} covariance of {settings['uncertainty_samples_per_member']} "
        "sample(s) per member"
    )


def _by_outcome(by_outcome: dict | None) -> str:
    """Alarmed episodes among the successful and the failed nominal ones (absent from older results)."""
    if not by_outcome:
        return ""
    parts = [
        f"{rates['alarmed_episodes']} of {rates['episodes']} {outcome}"
        for outcome, rates in by_outcome.items()
        if rates["episodes"]
    ]
    return f" (alarmed episodes: {', '.join(parts)})" if parts else ""


def _end_of_task_lines(end: dict | None) -> list[str]:
    """Where the nominal maxima fall (absent from results written before it was kept)."""
    if not end:
        return []
    if math.isnan(end["share_of_successful_episodes"]):
        return ["", "No nominal episode succeeded, so none says where its largest score falls."]
    return [
        "",
        f"The largest score of {_fmt(end['share_of_successful_episodes'])} of the successful nominal episodes "
        f"falls in their last {end['end_steps']} control steps (the end of the task).",
    ]


def _insertion_lines(insertion: dict | None) -> list[str]:
    """Where the policy's needle crossed the tissue (absent from results written before it was kept)."""
    if not insertion:
        return []
    entry, exit_ = insertion["entry_error_mm"], insertion["exit_error_mm"]
    return [
        f"Where the needle crossed the tissue, over the policy's nominal episodes: entry within "
        f"{_fmt(insertion['entry_tolerance_mm'])} mm of the mark in {_fmt(insertion['entry_within_tolerance'])} "
        f"(median {_fmt(entry['median'])} mm [{_fmt(entry['q25'])}, {_fmt(entry['q75'])}]), exit within "
        f"{_fmt(insertion['exit_tolerance_mm'])} mm in {_fmt(insertion['exit_within_tolerance'])} (median "
        f"{_fmt(exit_['median'])} mm [{_fmt(exit_['q25'])}, {_fmt(exit_['q75'])}]), both in "
        f"{_fmt(insertion['both_within_tolerance'])}; {insertion['never_entered']} never entered, "
        f"{insertion['never_emerged']} never emerged.",
        "",
    ]


def render_report(result: dict) -> str:
    """``report.md``: the results tables and the figures."""
    nominal = result["nominal"]
    low, high = nominal["success_rate_wilson95"]
    e_low, e_high = nominal["expert_success_rate_wilson95"]
    cal = result["calibration"]
    lines = [
        "# Results: safe, uncertainty-aware needle insertion",
        "",
        f"Policy: `{result['policy_path']}`. Gate: {cal['model']} model of the {cal['score_name']} score "
        f"({cal['space']} space{_settings_note(cal)}), {cal['mode']} mode, alpha {cal['alpha']}, "
        f"threshold {_fmt(cal['threshold'], 4)}.",
        "",
        "## In distribution (nominal)",
        "",
        "| | episodes | success | 95% Wilson interval |",
        "|---|---|---|---|",
        f"| policy | {nominal['episodes']} | {_fmt(nominal['success_rate'])} | [{_fmt(low)}, {_fmt(high)}] |",
        f"| scripted expert | {nominal['expert_episodes']} | {_fmt(nominal['expert_success_rate'])} | "
        f"[{_fmt(e_low)}, {_fmt(e_high)}] |",
        "",
        f"False alarms on nominal episodes: {_fmt(nominal['false_alarms']['per_step'])} per step, "
        f"{_fmt(nominal['false_alarms']['per_episode'])} per episode{_by_outcome(nominal.get('false_alarms_by_outcome'))}.",
        *_end_of_task_lines(nominal.get("score_max_in_last_steps")),
        "",
        *_insertion_lines(nominal.get("insertion")),
        "## Out of distribution (gate reporting, as in the paper)",
        "",
        "| experiment | scenario | runs | AUROC vs nominal [95% interval] | AUROC over common steps | TPR at threshold [95% interval] | detection delay (steps), median [IQR] |",
        "|---|---|---|---|---|---|---|",
    ]
    for exp_id, entry in result["experiments"].items():
        d = entry["detection_delay_steps"]
        delay = f"{_fmt(d['median'])} [{_fmt(d['q25'])}, {_fmt(d['q75'])}] (n={d['n']})" if d["n"] else "none"
        lines.append(
            f"| {exp_id} | {entry['scenario']} | {entry['runs']} | "
            f"{_fmt(entry['auroc'])}{_interval(entry.get('auroc_interval95'))} | "
            f"{_fmt(entry.get('auroc_common_steps'))} | "
            f"{_fmt(entry['tpr_at_threshold'])}{_interval(entry.get('tpr_wilson95'))} | {delay} |"
        )
    lines += [
        "",
        "AUROC vs nominal compares each episode's largest score (interval: DeLong's variance); the TPR's "
        "interval is Wilson's. A perturbed run whose throw never "
        "finishes (a dropped needle) goes on to the time limit, past where nominal episodes end. AUROC "
        "over common steps compares each pair of episodes over the control steps both lasted.",
    ]
    lines += ["", "## Control barrier function (experiment 4)", ""]
    replay = result["cbf"]["offline_replay"]
    lines.append(
        f"Offline replay: reference h_min {_fmt(replay.get('h_min_reference'))}, filtered h_min "
        f"{_fmt(replay.get('h_min_safe'))}."
    )
    lines += [
        "",
        "| live arm | runs | violations (h < 0 at a physics step) | min h | intervention rate | tissue strain (m), median |",
        "|---|---|---|---|---|---|",
    ]
    for arm, entry in result["cbf"]["live"].items():
        lines.append(
            f"| {arm} | {entry['runs']} | {entry['violations']} | {_fmt(entry['h_min'])} | "
            f"{_fmt(entry.get('intervention_rate'))} | {_fmt(entry['tissue_strain_m']['median'])} |"
        )
    lines += [
        "",
        "## Gate enforced, scripted surgeon taking over",
        "",
        "| scenario | runs | autonomous success | handover rate | handover step, median | needle in tissue at handover | success after handover | overall success |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for scenario, entry in result["gate_enforced"].items():
        step = (entry.get("handover_step") or {}).get("median")
        lines.append(
            f"| {scenario} | {entry['runs']} | {_fmt(entry['autonomous_success_rate'])} | {_fmt(entry['handover_rate'])} | "
            f"{_fmt(step)} | {_fmt(entry.get('handover_in_tissue_rate'))} | "
            f"{_fmt(entry['success_after_handover_rate'])} | {_fmt(entry['success_rate'])} |"
        )
    lines += ["", "## Figures", ""]
    for exp_id, name in result["figures"].items():
        lines.append(f"![experiment {exp_id}]({name})")
    lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=ExperimentsConfig, args=argv, exit_on_error=False)
    result = run_experiments(cfg)
    print((cfg.output_dir / "report.md").read_text())
    print(f"Figures, metrics.json and report.md in {cfg.output_dir} ({result['seconds']} s).")
