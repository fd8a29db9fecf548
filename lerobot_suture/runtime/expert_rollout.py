"""Roll out the scripted expert in a scenario and keep what a person wants to look at."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field

import gymnasium as gym
import numpy as np

from lerobot_suture.expert import ExpertConfig, ScriptedExpert
from lerobot_suture.registration import ENV_ID


@dataclass(frozen=True)
class ExpertStep:
    """One control step of the expert: the observation it acted on, its action and what followed."""

    obs: dict
    needle_keypoints: np.ndarray | None  # (6,) the needle in the image of ``obs`` (privileged), if asked for
    action: np.ndarray
    reward: float
    terminated: bool
    truncated: bool
    info: dict

    @property
    def done(self) -> bool:
        return self.terminated or self.truncated


def iter_expert_steps(
    env: gym.Env,
    expert: ScriptedExpert,
    obs: dict,
    steps_after_success: int = 0,
    needle_keypoints: bool = False,
) -> Iterator[ExpertStep]:
    """Yield the expert's steps from ``obs``, the observation ``env.reset`` just returned, to the
    episode's end.

    Args:
        steps_after_success: control steps to go on after the step the insertion succeeds (where the env
            terminates); the last of them is yielded as the terminal step. 0: end at success.
        needle_keypoints: also locate the needle in the image of each step's observation
            (``SutureEnv.needle_keypoints_in_image``; a dataset's training target). Otherwise None.
    """
    if steps_after_success < 0:
        raise ValueError(f"`steps_after_success` must be >= 0. Got {steps_after_success}.")
    expert.reset(env)
    remaining = None  # control steps left once the insertion has succeeded
    while True:
        keypoints = env.unwrapped.needle_keypoints_in_image() if needle_keypoints else None
        action = expert.act(env)
        next_obs, reward, terminated, truncated, info = env.step(action)
        if remaining is not None:
            remaining -= 1
        elif terminated and info["is_success"]:
            remaining = steps_after_success
        if remaining is not None:
            terminated = remaining == 0  # the episode, as recorded, ends after the extra steps
        yield ExpertStep(obs, keypoints, action, float(reward), bool(terminated), bool(truncated), info)
        if terminated or truncated:
            return
        obs = next_obs


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
) -> ExpertEpisode:
    """Run the expert (default settings unless ``expert_config``) for one episode; keep ``n_frames``
    evenly spaced endoscope frames."""
    own_env = env is None
    if own_env:
        env = gym.make(
            ENV_ID, obs_type="state", scenario=scenario, render_size=frame_size, disable_env_checker=True
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
