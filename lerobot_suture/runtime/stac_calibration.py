"""``lerobot-suture calibrate-stac``: fit the STAC gate of any chunking LeRobot policy on nominal rollouts.

Rolls the policy out in the nominal scenario on fresh seeds, scores every chunk it predicts against the one
before (:class:`~lerobot_suture.safety.ood.chunk_consistency.ChunkConsistencyMonitor`, on the chunks the
policy's own inference produced: :class:`~lerobot_suture.safety.ood.chunk_consistency.ChunkCapture`), and sets
the per-episode threshold at the split-conformal quantile of the episodes' maxima. Measures the false-alarm
rate on further held-out episodes and writes ``stac_calibration.json`` and ``stac_calibration_report.json``
beside the policy, where ``lerobot-rollout --strategy.type=gated_dagger`` reads it.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
from tqdm import tqdm

from lerobot_suture.runtime.config import PolicyCommandConfig
from lerobot_suture.runtime.seeds import fresh_seeds
from lerobot_suture.safety.ood.calibration import conformal_episode_threshold
from lerobot_suture.safety.ood.chunk_consistency import (
    ChunkCapture,
    ChunkConsistencyMonitor,
    StacCalibration,
    chunk_source,
)

REPORT_FILE = "stac_calibration_report.json"
SEED_OFFSET = 400_000
"""Calibration seeds are fresh seeds from this offset on (apart from the env path's other fresh seeds)."""


@dataclass
class CalibrateStacConfig(PolicyCommandConfig):
    """``lerobot-suture calibrate-stac`` flags, besides ``--policy.path`` (a chunking policy) and ``--device``.

    Args:
        calibration_episodes: nominal episodes the threshold is fitted on (>= 20 at alpha 0.05).
        holdout_episodes: further nominal episodes the false-alarm rate is measured on.
        alpha: per-episode false-alarm rate the threshold is set for, in (0, 0.5).
        bandwidth: STAC's kernel bandwidth per dimension (normalized action units, > 0).
    """

    writes_to_policy: ClassVar[bool] = True

    calibration_episodes: int = 100
    holdout_episodes: int = 20
    alpha: float = 0.05
    bandwidth: float = 0.5

    def __post_init__(self):
        super().__post_init__()
        if self.calibration_episodes < 1 or self.holdout_episodes < 0:
            raise ValueError(
                f"`calibration_episodes` must be >= 1 and `holdout_episodes` >= 0. Got "
                f"{self.calibration_episodes}, {self.holdout_episodes}."
            )


@dataclass
class StacEpisode:
    """One episode's STAC scores: per predicted chunk, and what happened."""

    seed: int
    scores: list[float]
    success: bool
    steps: int

    @property
    def max_score(self) -> float:
        return max(self.scores, default=0.0)


class StacScorer:
    """A policy runner with STAC watching the chunks its policy predicts."""

    def __init__(self, runner, bandwidth: float):
        self.runner = runner
        owner, method, start = chunk_source(runner.policy)
        self.capture = ChunkCapture(owner, method)
        shift = int(getattr(runner.policy.config, "n_action_steps", 1))
        self.monitor = ChunkConsistencyMonitor(shift, start, bandwidth)

    def episode(self, env, seed: int) -> StacEpisode:
        """Roll the policy out from ``seed`` until the episode ends, scoring every new chunk."""
        import torch

        torch.manual_seed(seed)
        self.runner.reset()
        self.monitor.reset()
        observation, _ = env.reset(seed=seed)
        scores, seen, steps, info = [], self.capture.chunks, 0, {}
        done = False
        while not done:
            action = self.runner.act(observation)
            if self.capture.chunks > seen:
                seen = self.capture.chunks
                scores.append(self.monitor.update(self.capture.last))
            observation, _, terminated, truncated, info = env.step(action)
            steps += 1
            done = terminated or truncated
        return StacEpisode(seed, scores, bool(info.get("is_success", False)), steps)


def run_stac_calibration(cfg: CalibrateStacConfig) -> dict:
    """Fit the threshold, write the calibration and its report beside the policy; returns the report."""
    from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy
    from lerobot_suture.runtime.rollout import make_scenario_env

    runner = PolicyRunner.from_pretrained(cfg.policy.path, GateMode.REPORT, cfg.device)
    scorer = StacScorer(runner, cfg.bandwidth)
    env = make_scenario_env(env_kwargs_for_policy(runner.policy.config), "nominal")
    seeds = fresh_seeds(cfg.calibration_episodes + cfg.holdout_episodes, start=SEED_OFFSET)
    try:
        episodes = [
            scorer.episode(env, seed) for seed in tqdm(seeds, desc="STAC calibration", unit="episode")
        ]
    finally:
        env.close()
    fit, held_out = episodes[: cfg.calibration_episodes], episodes[cfg.calibration_episodes :]
    threshold = conformal_episode_threshold([e.max_score for e in fit], cfg.alpha)
    config = runner.policy.config
    calibration = StacCalibration(
        threshold=threshold,
        bandwidth=cfg.bandwidth,
        alpha=cfg.alpha,
        episodes=len(fit),
        policy_type=str(config.type),
        n_action_steps=int(getattr(config, "n_action_steps", 1)),
    )
    path = calibration.save(cfg.policy.path)
    report = {
        "calibration": calibration.__dict__,
        "calibration_seeds": [e.seed for e in fit],
        "holdout_seeds": [e.seed for e in held_out],
        "calibration_success_rate": float(np.mean([e.success for e in fit])),
        "holdout_false_alarm_rate": float(np.mean([e.max_score > threshold for e in held_out]))
        if held_out
        else math.nan,
        "calibration_file": str(path),
    }
    (Path(cfg.policy.path) / REPORT_FILE).write_text(json.dumps(report, separators=(",", ":")) + "\n")
    return report
