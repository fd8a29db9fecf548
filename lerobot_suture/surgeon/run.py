"""A policy run with a surgeon in the loop (``lerobot-suture surgeon-run``) and the env driven by hand
(``lerobot-suture teleop``), each optionally recorded as a LeRobotDataset and shown live in rerun."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym

from lerobot_suture.registration import ENV_ID
from lerobot_suture.runtime.config import PolicyCommandConfig
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.sim.scenarios import SCENARIOS
from lerobot_suture.surgeon.surgeons import SURGEON_CHOICES, make_surgeon
from lerobot_suture.surgeon.teleop_mapping import TeleopMappingConfig

logger = logging.getLogger(__name__)


@dataclass
class SessionConfig:
    """Settings shared by ``surgeon-run`` and ``teleop``.

    Args:
        scenario: the env's scenario (``sim.scenarios.SCENARIOS``).
        episodes: episodes to run, >= 1.
        seed: env seed of the first episode (episode k: seed + k).
        max_steps: control steps per episode at most (10 Hz), >= 1.
        cbf: filter every command with the CBF (the surgeon's too).
        record_root: record the episodes as a LeRobotDataset into this new directory (None: do not).
        repo_id: the recorded dataset's id.
        video: store the endoscope as MP4 in the recording (false: PNG frames).
        display: show the live view (rerun's viewer; needs a display).
        view_path: write the live view to this ``.rrd`` file instead of showing it.
        mapping: speeds of the teleoperator's commands (m/s, rad/s).
    """

    scenario: str = "nominal"
    episodes: int = 1
    seed: int = 3_000_000
    max_steps: int = 300
    cbf: bool = True
    record_root: Path | None = None
    repo_id: str = "local/suture_surgeon_run"
    video: bool = True
    display: bool = True
    view_path: Path | None = None
    mapping: TeleopMappingConfig = field(default_factory=TeleopMappingConfig)

    def __post_init__(self):
        if self.scenario not in SCENARIOS:
            raise ValueError(f"`scenario` must be one of {tuple(SCENARIOS)}. Got {self.scenario!r}.")
        if self.episodes < 1:
            raise ValueError(f"`episodes` must be >= 1. Got {self.episodes}.")
        if self.max_steps < 1:
            raise ValueError(f"`max_steps` must be >= 1. Got {self.max_steps}.")
        if self.record_root is not None and Path(self.record_root).exists():
            raise FileExistsError(f"`record_root` {self.record_root} exists; name a new directory.")


@dataclass
class SurgeonRunConfig(SessionConfig, PolicyCommandConfig):
    """``lerobot-suture surgeon-run``: ``--policy.path=DIR --surgeon=keyboard|gamepad|expert|none``.

    Args (and those of :class:`~lerobot_suture.runtime.config.PolicyCommandConfig`; the policy is a
    trained, calibrated ensemble, ``lerobot-suture calibrate``):
        surgeon: who takes over when the gate releases control (and at a key press).
        enforce: the gate releases control on its first O.O.D. decision (false: it only reports).
    """

    surgeon: str = "keyboard"
    enforce: bool = True

    def __post_init__(self):
        SessionConfig.__post_init__(self)
        PolicyCommandConfig.__post_init__(self)
        if self.surgeon not in SURGEON_CHOICES:
            raise ValueError(f"`surgeon` must be one of {SURGEON_CHOICES}. Got {self.surgeon!r}.")


@dataclass
class TeleopConfig(SessionConfig):
    """``lerobot-suture teleop --teleop=keyboard|gamepad``: the env driven by hand, no policy.

    Args:
        teleop: the teleoperator, ``keyboard`` or ``gamepad``.
        obs_type: the env's observation layout; image_size: its endoscope side (px).
    """

    teleop: str = "keyboard"
    obs_type: str = "pixels_agent_pos"
    image_size: int = 96

    def __post_init__(self):
        super().__post_init__()
        if self.teleop not in ("keyboard", "gamepad"):
            raise ValueError(f"`teleop` must be one of ('keyboard', 'gamepad'). Got {self.teleop!r}.")


def _env(cfg: SessionConfig, env_kwargs: dict) -> gym.Env:
    cbf = CBFConfig(enabled=True) if cfg.cbf else None
    return gym.make(ENV_ID, disable_env_checker=True, scenario=cfg.scenario, cbf=cbf, **env_kwargs)


def _extras(cfg: SessionConfig, env_kwargs: dict):
    from lerobot_suture.surgeon.live_view import LiveView
    from lerobot_suture.surgeon.record_run import RunRecorder

    recorder = None
    if cfg.record_root is not None:
        recorder = RunRecorder(
            cfg.repo_id, cfg.record_root, env_kwargs["obs_type"], env_kwargs.get("image_size", 96), cfg.video
        )
    view = LiveView(cfg.view_path) if (cfg.display or cfg.view_path is not None) else None
    return recorder, view


def _close(recorder, view, surgeon, env) -> None:
    """Finish what a session opened, the recording first: its finished episodes are kept."""
    if recorder is not None:
        recorder.finalize()
    if view is not None:
        view.close()
    surgeon.close()
    env.close()


def surgeon_run(cfg: SurgeonRunConfig) -> list:
    from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy
    from lerobot_suture.surgeon.session import run_surgeon_episode

    runner = PolicyRunner.from_pretrained(
        cfg.policy.path, GateMode.of(cfg.enforce), cfg.device, cfg.policy.overrides
    )
    env_kwargs = env_kwargs_for_policy(runner.policy.config)
    surgeon = make_surgeon(cfg.surgeon, cfg.mapping)
    env = _env(cfg, env_kwargs)
    recorder, view = _extras(cfg, env_kwargs)
    logs = []
    try:
        for k in range(cfg.episodes):
            log = run_surgeon_episode(env, runner, surgeon, cfg.seed + k, cfg.max_steps, recorder, view)
            logs.append(log)
            handovers = ", ".join(
                f"step {s}: {a.name.lower()} -> {b.name.lower()} ({why})" for s, a, b, why in log.handovers
            )
            logger.info(
                "episode %d (seed %d): success %s; %s", k, log.seed, log.success, handovers or "no handover"
            )
    finally:
        _close(recorder, view, surgeon, env)
    return logs


def teleop(cfg: TeleopConfig) -> list[bool]:
    """Drive the env by hand; returns each episode's success."""
    from lerobot_suture.surgeon.session import run_surgeon_episode

    env_kwargs = {"obs_type": cfg.obs_type, "image_size": cfg.image_size}
    surgeon = make_surgeon(cfg.teleop, cfg.mapping)
    env = _env(cfg, env_kwargs)
    recorder, view = _extras(cfg, env_kwargs)
    successes = []
    try:
        for k in range(cfg.episodes):
            log = run_surgeon_episode(env, None, surgeon, cfg.seed + k, cfg.max_steps, recorder, view)
            successes.append(log.success)
            logger.info("episode %d (seed %d): success %s", k, cfg.seed + k, successes[-1])
    finally:
        _close(recorder, view, surgeon, env)
    return successes
