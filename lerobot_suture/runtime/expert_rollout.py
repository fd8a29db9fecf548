"""Roll out the scripted expert in a scenario and keep what a person wants to look at (its outcome and
endoscope frames along it); the stepping itself is :func:`lerobot_suture.expert.iter_expert_steps`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import gymnasium as gym
import numpy as np

from lerobot_suture.expert import ExpertConfig, ScriptedExpert, iter_expert_steps
from lerobot_suture.sim.tasks import DEFAULT_TASK, task_spec


@dataclass
class ExpertEpisode:
    """One expert episode: its outcome, and endoscope frames sampled along it."""

    seed: int
    scenario: str
    success: bool
    steps: int
    entry_error_m: float
    exit_error_m: float
    tissue_strain_m: float
    perturbation_onset_step: int | None
    frames: list[np.ndarray] = field(default_factory=list, repr=False)

    def summary(self) -> dict:
        def finite(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        return {
            "seed": self.seed,
            "scenario": self.scenario,
            "success": self.success,
            "steps": self.steps,
            "entry_error_m": finite(self.entry_error_m),
            "exit_error_m": finite(self.exit_error_m),
            "tissue_strain_m": float(self.tissue_strain_m),
            "perturbation_onset_step": self.perturbation_onset_step,
        }


def run_expert_episode(
    seed: int,
    scenario: str = "nominal",
    n_frames: int = 0,
    frame_size: int = 160,
    env: gym.Env | None = None,
    expert_config: ExpertConfig | None = None,
    task: str = DEFAULT_TASK,
) -> ExpertEpisode:
    """Run the expert (default settings unless ``expert_config``) for one episode of ``task`` (unless an
    ``env`` is given); keep ``n_frames`` evenly spaced endoscope frames."""
    own_env = env is None
    if own_env:
        env = gym.make(
            task_spec(task).gym_id,
            obs_type="state",
            scenario=scenario,
            render_size=frame_size,
            disable_env_checker=True,
        )
    try:
        obs, info = env.reset(seed=seed)
        frames = [env.render()] if n_frames else []
        onset = 0 if env.unwrapped.scenario.perturbed else None
        steps = 0
        for steps, step in enumerate(iter_expert_steps(env, ScriptedExpert(expert_config), obs), start=1):
            info = step.info
            if onset is None and info["perturbed"]:
                onset = steps - 1
            if n_frames:
                frames.append(env.render())
        if n_frames:
            keep = np.linspace(0, len(frames) - 1, n_frames).round().astype(int)
            frames = [frames[i] for i in keep]
        return ExpertEpisode(
            seed=seed,
            scenario=scenario,
            success=bool(info["is_success"]),
            steps=steps,
            entry_error_m=float(info["entry_error_m"]),
            exit_error_m=float(info["exit_error_m"]),
            tissue_strain_m=float(info["tissue_strain"]),
            perturbation_onset_step=onset,
            frames=frames,
        )
    finally:
        if own_env:
            env.close()
