"""``lerobot-suture cbf-replay``: the paper's experiment 4, offline.

Records a reference needle-tip trajectory in the env (the scripted expert's throw, turned unsafe by
a sideways pull once the needle is in tissue: what a bad policy prediction would do), filters it
offline through the CBF and writes the paper's three-panel figure plus its metrics as JSON.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lerobot_suture.experiments.sideways_pull import SidewaysPull
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.safety.cbf_replay import replay_and_plot
from lerobot_suture.safety.cbf_wrapper import CBFActionWrapper
from lerobot_suture.sim.suture_env import SutureEnv

logger = logging.getLogger(__name__)


@dataclass
class CBFReplayConfig:
    """Args:
    output_dir: where ``cbf_replay.png`` and ``cbf_replay.json`` go.
    seed: env seed of the recorded episode.
    pull_distance: sideways pull (m) the reference makes once the needle is in tissue.
    steps_in_tissue: control steps the needle spends in tissue before the pull.
    pull_steps: control steps recorded after the pull begins.
    cbf: the filter's settings (``enabled`` is ignored: the replay always filters).
    """

    output_dir: Path = Path("outputs/cbf")
    seed: int = 0
    pull_distance: float = 0.02
    steps_in_tissue: int = 3
    pull_steps: int = 15
    cbf: CBFConfig = field(default_factory=CBFConfig)


def record_reference(cfg: CBFReplayConfig) -> tuple[np.ndarray, CBFActionWrapper]:
    """Tip positions (T, 3) m of the unsafe reference, and the (monitoring-only) env it ran in."""
    env = CBFActionWrapper(SutureEnv(obs_type="state"), CBFConfig(enabled=False))
    _, info = env.reset(seed=cfg.seed)
    policy = SidewaysPull(cfg.pull_distance, cfg.steps_in_tissue)
    policy.reset(env)
    tips = [info["needle_tip_pos"]]
    pulled = 0
    while pulled < cfg.pull_steps:
        action = policy.act(env)
        pulled += int(policy.pulling)
        _, _, terminated, truncated, info = env.step(action)
        tips.append(info["needle_tip_pos"])
        if terminated or truncated:
            break
    return np.asarray(tips), env


def run_cbf_replay(cfg: CBFReplayConfig) -> dict:
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    tips, env = record_reference(cfg)
    center, axes, rotation = CBFActionWrapper(env.env, cfg.cbf).safe_set()
    u = env.unwrapped
    metrics = replay_and_plot(
        tips,
        u.control_dt,
        center,
        cfg.cbf.semi_axes,
        rotation,
        cfg.cbf.alpha,
        cfg.output_dir / "cbf_replay.png",
        margin=cfg.cbf.margin,
        discrete=cfg.cbf.discrete,
        substeps=u.n_substeps,
        title=f"CBF offline replay (seed {cfg.seed}, {cfg.pull_distance * 1000:g} mm sideways pull)",
    )
    env.close()
    metrics = {k: (str(v) if isinstance(v, Path) else v) for k, v in metrics.items()}
    (cfg.output_dir / "cbf_replay.json").write_text(json.dumps(metrics, separators=(",", ":"), default=float))
    return metrics
