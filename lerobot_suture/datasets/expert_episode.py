"""One expert episode for the dataset: the scripted expert rolled out from a seed, its frames in the
dataset's layout, and whether it is kept (a success that holds through the steps recorded after it) or
discarded, and why."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from lerobot_suture.datasets.features import (
    ACTION_KEY,
    DONE_KEY,
    ENV_STATE_KEY,
    IMAGE_KEY,
    NEEDLE_KEYPOINTS_KEY,
    REWARD_KEY,
    STATE_KEY,
    SUCCESS_KEY,
    WRIST_IMAGE_KEY,
)
from lerobot_suture.expert import iter_expert_steps
from lerobot_suture.sim import task
from lerobot_suture.sim.extraction import STRAIN_BOUND
from lerobot_suture.sim.pickup import grasp_ready_for_throw
from lerobot_suture.sim.tasks import DEFAULT_TASK, task_spec


@dataclass
class ExpertEpisodeFrames:
    """One expert episode as dataset frames, with its outcome."""

    seed: int
    frames: list[dict]
    success: bool
    info: dict
    reason: str | None = None
    """Why the episode failed (a short category), None on success."""
    detail: str | None = None

    @property
    def length(self) -> int:
        return len(self.frames)


def _pickup_failure_reason(info: dict, steps: int) -> tuple[str, str]:
    """(category, detail) of a failed pickup, from the env's final ``info``."""
    if not info["needle_grasped"]:
        return "needle not held", f"the jaw did not hold the needle after {steps} steps"
    angle, depth, roll = info["grasp_parameters"]
    detail = f"arc angle {math.degrees(angle):.1f} deg, depth {depth * 1e3:.2f} mm, roll {roll:.3f} rad"
    if not grasp_ready_for_throw(tuple(info["grasp_parameters"]), reversed_grasp=False):
        return "grasp off the ranges", detail
    return "needle not lifted", f"held ({detail}) but not lifted clear within {steps} steps"


def _extraction_failure_reason(info: dict, steps: int) -> tuple[str, str]:
    """(category, detail) of a failed extraction, from the env's final ``info``."""
    strain = f"tissue strain {info['tissue_strain'] * 1e3:.2f} mm"
    if info["tissue_strain"] > STRAIN_BOUND:
        return "tissue strained", f"{strain} > {STRAIN_BOUND * 1e3:g} mm"
    if info["needle_in_tissue"]:
        return "needle still in tissue", f"not out within {steps} steps ({strain})"
    return (
        "needle not held or out the wrong way",
        f"out of the tissue but not held, or not by the exit ({strain})",
    )


def _running_suture_failure_reason(info: dict, steps: int) -> tuple[str, str]:
    """(category, detail) of a failed running suture, from the env's final ``info``."""
    results = info["throw_results"]
    off = [r for r in results if not r["on_marks"]]
    if off:
        r = off[0]
        return (
            f"throw {r['throw'] + 1} off the marks",
            f"entry error {r['entry_error_m'] * 1e3:.2f} mm, exit error {r['exit_error_m'] * 1e3:.2f} mm",
        )
    return (
        "time limit",
        f"{len(results)} of 4 throws done within {steps} steps (throw phase {info['throw_phase']})",
    )


def _failure_reason(info: dict, steps: int) -> tuple[str, str]:
    """(category, detail) of a failed insertion, from the env's final ``info``."""
    entry, exit_ = info["entry_error_m"], info["exit_error_m"]
    if not info["needle_grasped"]:
        return "needle dropped", f"the jaw lost the needle; episode ended after {steps} steps"
    crossings = (
        ("entry", entry, task.ENTRY_TOLERANCE, "needle never entered the tissue"),
        ("exit", exit_, task.EXIT_TOLERANCE, "needle did not emerge"),
    )
    for name, error, tolerance, missing in crossings:
        if not math.isfinite(error):
            return missing, f"no {name} within {steps} steps"
        if error > tolerance:
            return (
                f"{name} error above tolerance",
                f"{name} error {error * 1e3:.2f} mm > {tolerance * 1e3} mm",
            )
    return "time limit", f"not done within {steps} steps (protrusion {info['protrusion_m'] * 1e3:.2f} mm)"


def make_env(
    obs_type: str,
    image_size: int,
    scenario: str,
    grasp: str = "narrow",
    appearance: dict | None = None,
    task: str = DEFAULT_TASK,
    wrist_camera: bool = False,
    marks: bool = False,
    subtask: bool = False,
    relative_actions: bool = False,
    regrasp_target: bool = False,
    regrasp_from: str = "marks",
):
    """The env the dataset is recorded in (``gym.make`` of the task's gym id); ``appearance`` the fields of
    an :class:`~lerobot_suture.sim.appearance.AppearanceConfig` (None: all off)."""
    return gym.make(
        task_spec(task).gym_id,
        obs_type=obs_type,
        image_size=image_size,
        scenario=scenario,
        grasp=grasp,
        appearance=appearance,
        disable_env_checker=True,
        **({"wrist_camera": True} if wrist_camera else {}),
        **({"marks": True} if marks else {}),
        **({"subtask": True} if subtask else {}),
        **({"relative_actions": True} if relative_actions else {}),
        **({"regrasp_target": True} if regrasp_target else {}),
        **({"regrasp_from": regrasp_from} if regrasp_from != "marks" else {}),
    )


def expert_episode_frames(
    env,
    expert,
    seed: int,
    on_step: Callable[[], None] | None = None,
    steps_after_success: int = 0,
) -> ExpertEpisodeFrames:
    """Run the expert for one episode from ``env.reset(seed=seed)``; frames in dataset layout.

    Args:
        env: the (wrapped) env from :func:`make_env`.
        expert: a :class:`~lerobot_suture.expert.ScriptedExpert`.
        seed: env seed.
        on_step: called after every control step (progress).
        steps_after_success: control steps recorded after the insertion succeeds; the episode counts as a
            success only if all of them are recorded and the insertion holds through every one.
    """
    obs, info = env.reset(seed=seed)
    instruction = env.unwrapped.task_description
    frames = []
    # The needle's place in the image is recorded with the image (a target for the image encoders).
    keypoints = "pixels" in obs
    for step in iter_expert_steps(env, expert, obs, steps_after_success, needle_keypoints=keypoints):
        frame = {
            STATE_KEY: step.obs["agent_pos"],
            ACTION_KEY: np.asarray(step.action, dtype=np.float32),
            REWARD_KEY: np.array([step.reward], dtype=np.float32),
            SUCCESS_KEY: np.array([bool(step.info["is_success"])]),
            DONE_KEY: np.array([step.done]),
            "task": instruction,
        }
        if "pixels" in step.obs:
            frame[IMAGE_KEY] = step.obs["pixels"]["endoscope"]
            if "wrist" in step.obs["pixels"]:
                frame[WRIST_IMAGE_KEY] = step.obs["pixels"]["wrist"]
            frame[NEEDLE_KEYPOINTS_KEY] = step.needle_keypoints
        if "environment_state" in step.obs:
            frame[ENV_STATE_KEY] = step.obs["environment_state"]
        frames.append(frame)
        info = step.info
        if on_step is not None:
            on_step()
    rollout = ExpertEpisodeFrames(seed=seed, frames=frames, success=False, info=info)
    succeeded = [bool(f[SUCCESS_KEY][0]) for f in frames]
    if True not in succeeded:
        explain = {
            "pickup": _pickup_failure_reason,
            "extraction": _extraction_failure_reason,
            "running_suture": _running_suture_failure_reason,
        }.get(env.unwrapped.task_name, _failure_reason)
        rollout.reason, rollout.detail = explain(info, len(frames))
        return rollout
    first = succeeded.index(True)
    after = len(frames) - 1 - first
    if not all(succeeded[first:]):
        lost = first + succeeded[first:].index(False)
        rollout.reason = "success lost while driving on"
        rollout.detail = (
            f"succeeded at step {first + 1}, lost it at step {lost + 1} of the {steps_after_success} steps "
            "after success; record with a smaller --steps_after_success"
        )
    elif after < steps_after_success:
        rollout.reason = "time limit after success"
        rollout.detail = f"{after} of the {steps_after_success} steps after success fit in the time limit"
    else:
        rollout.success = True
    return rollout
