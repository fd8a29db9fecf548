"""One policy on the fixed test seeds: the gate enforced, the scripted surgeon taking over after a handover.

Per scenario: autonomous success (a success with no handover), overall success (the surgeon's rescues
count), handovers and surgeon control steps (10 Hz) per episode, episodes with an alarm (for ``nominal``
the false alarms), and, for each perturbed scenario, the episode-level AUROC of its uncertainty scores
against the nominal ones (:func:`~lerobot_suture.experiments.episode_metrics.ood_metrics`; once the gate has
released control the policy is not asked again, so an episode's score is its largest before the handover).
The surgeon here is :func:`~lerobot_suture.runtime.rollout.rollout_episodes`' (the default scripted expert), as in
``lerobot-suture experiments``; it only finishes what the policy handed over.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np

from lerobot_suture.dagger.config import SCENARIOS
from lerobot_suture.experiments import metrics
from lerobot_suture.experiments.episode_metrics import ood_metrics
from lerobot_suture.runtime.policy import GateMode, PolicyRunner
from lerobot_suture.runtime.rollout import SURGEON, EpisodeLog, make_scenario_env, rollout_seeds
from lerobot_suture.runtime.seeds import episode_seeds

NOMINAL = "nominal"


def evaluation_seeds(base: int, episodes: int) -> dict[str, list[int]]:
    """Scenario -> its test seeds: the same for every round and arm."""
    return {scenario: episode_seeds(base, group, episodes) for group, scenario in enumerate(SCENARIOS)}


def _mean(values) -> float:
    values = list(values)
    return float(np.mean(values)) if values else math.nan


def surgeon_steps(log: EpisodeLog) -> int:
    return sum(step.controller == SURGEON for step in log.steps)


def scenario_metrics(logs: list[EpisodeLog]) -> dict:
    return {
        "episodes": len(logs),
        "autonomous_success": _mean(log.autonomous_success for log in logs),
        "success": _mean(log.success for log in logs),
        "handovers_per_episode": _mean(log.handover_step is not None for log in logs),
        "surgeon_steps_per_episode": _mean(surgeon_steps(log) for log in logs),
        "alarms_per_episode": metrics.alarm_rates([[s.ood for s in log.steps] for log in logs])[
            "per_episode"
        ],
    }


def summarize(logs: dict[str, list[EpisodeLog]]) -> dict:
    """The evaluation's figures from the episodes of every scenario (``nominal`` among them)."""
    every = [log for scenario_logs in logs.values() for log in scenario_logs]
    result = {
        "scenarios": {scenario: scenario_metrics(scenario_logs) for scenario, scenario_logs in logs.items()},
        "overall": scenario_metrics(every),
        "nominal_false_alarms_per_episode": scenario_metrics(logs[NOMINAL])["alarms_per_episode"],
        "auroc": {},
        "episodes": {
            scenario: [
                {
                    "seed": log.seed,
                    "success": log.success,
                    "autonomous_success": log.autonomous_success,
                    "handover_step": log.handover_step,
                    "surgeon_steps": surgeon_steps(log),
                    "episode_score": metrics.episode_score(log.scores),
                }
                for log in scenario_logs
            ]
            for scenario, scenario_logs in logs.items()
        },
    }
    for scenario, scenario_logs in logs.items():
        if scenario != NOMINAL:
            ood = ood_metrics(logs[NOMINAL], scenario_logs)
            result["auroc"][scenario] = ood["auroc"]
            result["scenarios"][scenario]["auroc_common_steps"] = ood["auroc_common_steps"]
    return result


def evaluate(
    policy_dir: Path,
    env_kwargs: dict,
    seeds: dict[str, list[int]],
    batch_envs: int,
    workers: int,
    device: str,
    desc: str,
) -> dict:
    """Roll the calibrated policy out on ``seeds`` (scenario -> seeds), gate enforced, expert surgeon."""
    runner = PolicyRunner.from_pretrained(policy_dir, GateMode.ENFORCE, device)
    logs = {
        scenario: rollout_seeds(
            functools.partial(make_scenario_env, env_kwargs, scenario),
            runner,
            scenario_seeds,
            batch_envs,
            surgeon="expert",
            desc=f"{desc}, {scenario}",
            workers=workers,
        )
        for scenario, scenario_seeds in seeds.items()
    }
    result = summarize(logs)
    result["policy_path"] = str(policy_dir)
    result["threshold"] = float(runner.policy.ood_calibration.threshold)
    return result
