#!/usr/bin/env python
"""Does a trained ensemble look at the needle in the endoscope image?

The gate can only flag a dropped needle if the members' predictions depend on the needle they see. For
each checkpoint, the scripted expert drives nominal episodes (the training distribution); at a few
control steps the same state is shown to the ensemble twice, once as rendered and once with the
needle made invisible, with the same diffusion noise. A second noise draw on the unchanged image gives
the scale of the sampling noise to compare with, and the same state rendered with the phantom moved
3 mm is the positive control (a policy that servos to the phantom must respond to it). Per checkpoint it
prints one JSON line of medians over the probed frames:

- ``needle_pixels``: endoscope pixels (env image size) that change when the needle is hidden;
- ``hidden_shift_mm``: how far the ensemble's first predicted jaw position moves when the needle is
  hidden; ``noise_shift_mm``: how far it moves with another noise draw instead;
- ``phantom_shift_mm``: how far it moves when the phantom is shown 3 mm away instead (the control);
  ``phantom_score_ratio``: the uncertainty score then, over the score with the phantom in place;
- ``hidden_score_ratio``: the uncertainty score with the needle hidden over the score with it shown;
  ``noise_score_ratio``: the same for another noise draw;
- ``keypoint_error_px`` and ``hidden_keypoint_shift_px``, for a policy trained with the auxiliary needle
  target (``--policy.needle_keypoints_weight``; null otherwise): how far the members' mean estimate of
  the needle's tip, middle and tail lies from the true ones, and how far it moves when the needle is
  hidden (mean over the three points, image pixels at the env's image size). An encoder that finds the
  needle itself moves its estimate when the needle vanishes; one that infers it from the jaw does not;
- ``inserted``: the same medians over only the probed frames where the needle is already in the tissue
  (``frames`` of them; the fields are null when there is none). Experiment 3.2 moves the phantom in
  this phase, so its ``phantom_shift_mm`` says whether the members still watch the phantom there.

A ``hidden_shift_mm`` far below ``noise_shift_mm`` and a ``hidden_score_ratio`` of 1 mean that the
members ignore the needle, so its absence (experiment 1) is not out of distribution for them; a
``phantom_shift_mm`` well above ``hidden_shift_mm`` shows that the probe itself can see a response.

    python studies/benchmarks/needle_attention.py CHECKPOINT [CHECKPOINT ...]

CHECKPOINT is a ``pretrained_model`` directory, or a run's ``checkpoints`` directory (every step in it).
Probe seeds start at 3,000,000: disjoint from recording, calibration and test seeds.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from lerobot_policy_ensemble_diffusion.needle_keypoints import predict_needle_keypoints  # noqa: E402

import lerobot_suture  # noqa: E402
from lerobot_suture.expert import ScriptedExpert  # noqa: E402
from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy  # noqa: E402

NEEDS = "trained ensemble checkpoints (CHECKPOINT ...)"
PROBE_SEED_BASE = 3_000_000
PHANTOM_PROBE_SHIFT = np.array([0.003, 0.0, 0.0])
"""Displacement (m) of the phantom in the positive control: 1.5x the entry tolerance."""


def _prediction(runner: PolicyRunner, observation: dict, noise: torch.Tensor) -> tuple[np.ndarray, float]:
    """(first predicted jaw position (3,) in mm, uncertainty score) for one observation and noise."""
    runner.reset()
    runner.policy.select_action(runner.preprocess([observation]), noise=noise)
    prediction = runner.policy.last_prediction
    return prediction.unnormalized.mean[0, 0, :3].numpy() * 1e3, float(prediction.score[0])


def _keypoint_estimate(runner: PolicyRunner, observation: dict) -> np.ndarray | None:
    """The members' mean estimate of the needle keypoints, (3, 2) normalized; None without keypoint heads."""
    if runner.policy.needle_heads is None:
        return None
    estimate = predict_needle_keypoints(runner.policy, runner.preprocess([observation]))
    return estimate[0].float().mean(0).reshape(-1, 2).numpy()


def _phantom_moved_observation(sim) -> dict:
    """The current observation rendered with the phantom moved by ``PHANTOM_PROBE_SHIFT``, then put back."""
    import mujoco  # after lerobot_suture, which picks MuJoCo's GL backend

    position, yaw = sim.phantom_position.copy(), sim.phantom_yaw
    try:
        sim.set_phantom_pose(position + PHANTOM_PROBE_SHIFT, yaw)
        return sim.observe()  # places the moved mocap body (kinematics) before rendering
    finally:
        sim.set_phantom_pose(position, yaw)
        mujoco.mj_forward(sim.model, sim.data)  # the episode goes on from the phantom's true pose


def needle_attention(checkpoint: Path, episodes: int, probe_steps: list[int], device: str) -> dict:
    started = time.perf_counter()
    runner = PolicyRunner.from_pretrained(checkpoint, GateMode.REPORT, device)
    config = runner.policy.config
    env_kwargs = env_kwargs_for_policy(config)
    if "image_size" not in env_kwargs:
        raise ValueError(f"{checkpoint} reads no endoscope image: there is no needle for it to look at.")
    env = gym.make(lerobot_suture.ENV_ID, disable_env_checker=True, **env_kwargs)
    noise_shape = (
        1,
        config.n_members,
        config.uncertainty_samples_per_member,
        config.horizon,
        config.action_feature.shape[0],
    )
    rows = []
    for seed in range(PROBE_SEED_BASE, PROBE_SEED_BASE + episodes):
        observation, _ = env.reset(seed=seed)
        expert = ScriptedExpert()
        expert.reset(env)
        generator = torch.Generator().manual_seed(seed)
        for step in range(max(probe_steps) + 1):
            if step in probe_steps:
                noise, other_noise = (torch.randn(noise_shape, generator=generator) for _ in range(2))
                hidden = env.unwrapped.observe(needle_visible=False)
                moved = _phantom_moved_observation(env.unwrapped)
                shown_pos, shown_score = _prediction(runner, observation, noise)
                hidden_pos, hidden_score = _prediction(runner, hidden, noise)
                other_pos, other_score = _prediction(runner, observation, other_noise)
                moved_pos, moved_score = _prediction(runner, moved, noise)
                changed = observation["pixels"]["endoscope"] != hidden["pixels"]["endoscope"]
                shown_kp, hidden_kp = (
                    _keypoint_estimate(runner, observation),
                    _keypoint_estimate(runner, hidden),
                )
                keypoint_error = keypoint_shift = np.nan
                if shown_kp is not None:
                    px = env.unwrapped.image_size / 2  # pixels per normalized image unit
                    truth = env.unwrapped.needle_keypoints_in_image().reshape(-1, 2)
                    keypoint_error = px * np.linalg.norm(shown_kp - truth, axis=1).mean()
                    keypoint_shift = px * np.linalg.norm(hidden_kp - shown_kp, axis=1).mean()
                rows.append(
                    (
                        int(changed.any(-1).sum()),
                        np.linalg.norm(hidden_pos - shown_pos),
                        np.linalg.norm(other_pos - shown_pos),
                        np.linalg.norm(moved_pos - shown_pos),
                        hidden_score / shown_score,
                        other_score / shown_score,
                        moved_score / shown_score,
                        keypoint_error,
                        keypoint_shift,
                        float(env.unwrapped.needle_in_tissue),
                    )
                )
            observation, _, terminated, truncated, _ = env.step(expert.act(env))
            if terminated or truncated:
                break
    env.close()
    if not rows:
        raise ValueError(f"No frame was probed: every episode ended before the probe steps {probe_steps}.")
    rows = np.array(rows, dtype=float)
    inserted = rows[rows[:, -1] == 1.0]
    return {
        "checkpoint": str(checkpoint),
        **_medians(rows),
        "inserted": _medians(inserted),
        "seconds": round(time.perf_counter() - started, 1),
    }


def _medians(rows: np.ndarray) -> dict:
    """The report's medians over probed frames (one row each); nulls for no frame."""
    medians = np.median(rows, axis=0) if len(rows) else np.full(rows.shape[1], np.nan)

    def field(column: int, digits: int) -> float | None:
        return None if np.isnan(medians[column]) else round(float(medians[column]), digits)

    return {
        "frames": len(rows),
        "needle_pixels": field(0, 1),
        "hidden_shift_mm": field(1, 4),
        "noise_shift_mm": field(2, 4),
        "phantom_shift_mm": field(3, 4),
        "hidden_score_ratio": field(4, 4),
        "noise_score_ratio": field(5, 4),
        "phantom_score_ratio": field(6, 4),
        "keypoint_error_px": field(7, 2),
        "hidden_keypoint_shift_px": field(8, 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("checkpoints", nargs="+")
    parser.add_argument("--episodes", type=int, default=12)
    parser.add_argument("--probe-steps", default="5,15,25,35", help="control steps probed in each episode")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    sys.path.insert(0, str(Path(__file__).parent))
    from open_loop_error import checkpoint_dirs

    probe_steps = sorted({int(s) for s in args.probe_steps.split(",")})
    for checkpoint in checkpoint_dirs(args.checkpoints):
        result = needle_attention(checkpoint, args.episodes, probe_steps, args.device)
        print(json.dumps({"benchmark": "needle_attention", **result}), flush=True)


if __name__ == "__main__":
    main()
