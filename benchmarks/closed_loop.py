#!/usr/bin/env python
"""Closed-loop speed: control steps per second of the full loop on this machine.

The loop is the one the experiments run: the env rendering the 96 px endoscope image, an ensemble of
5 members (CPU preset: DDIM with 10 steps at inference, a chunk every 4 steps) behind LeRobot's pre-
and post-processors, the O.O.D. gate, and the CBF filtering the tip velocity (with its 100 Hz
re-tracking). The weights are untrained (latency does not depend on them); the policy is saved and
loaded as lerobot-train's output is. Prints JSON. Target: >= 10 control steps per second
(the paper's simulator loop ran at 1 Hz).

    python benchmarks/closed_loop.py [--steps 200] [--threads 2] [--samples-per-member K]
        [--vision-backbone-stages S] [--prior-scale B]

The last two build the members as the reference run's flags do (defaults: the CPU preset's).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from _policy_builders import fake_dataset_stats, save_untrained_policy  # noqa: E402

import lerobot_suture  # noqa: E402
from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy  # noqa: E402
from lerobot_suture.safety.cbf_config import CBFConfig  # noqa: E402
from lerobot_suture.safety.ood.calibration import fit_calibration  # noqa: E402
from lerobot_suture.safety.ood.calibration_file import save_calibration  # noqa: E402


def saved_ensemble(
    directory: Path, n_members: int, samples_per_member: int | None = None, **overrides
) -> Path:
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from ensemble_latency import load_preset_config

    if samples_per_member is not None:
        overrides["uncertainty_samples_per_member"] = samples_per_member
    config = load_preset_config("cpu", n_members=n_members, device="cpu", **overrides)
    save_untrained_policy(config, fake_dataset_stats(), directory)
    rng = np.random.default_rng(0)
    save_calibration(fit_calibration(rng.lognormal(0, 0.3, 200), model="lognormal"), directory)
    return directory


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--members", type=int, default=5)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument(
        "--samples-per-member", type=int, default=None, help="K chunks per member (default: the preset's)"
    )
    parser.add_argument("--vision-backbone-stages", type=int, default=4)
    parser.add_argument("--prior-scale", type=float, default=0.0)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    with tempfile.TemporaryDirectory() as tmp:
        policy_dir = saved_ensemble(
            Path(tmp) / "pretrained_model",
            args.members,
            args.samples_per_member,
            vision_backbone_stages=args.vision_backbone_stages,
            prior_scale=args.prior_scale,
        )
        runner = PolicyRunner.from_pretrained(policy_dir, GateMode.REPORT)
        env = gym.make(
            lerobot_suture.ENV_ID,
            disable_env_checker=True,
            cbf=CBFConfig(enabled=True),
            **env_kwargs_for_policy(runner.policy.config),
        )
        observation, _ = env.reset(seed=0)
        runner.reset()
        for _ in range(8):  # warm up (renderer, fused members)
            observation, *_ = env.step(runner.act(observation))
        observation, _ = env.reset(seed=1)
        runner.reset()
        start, steps, predictions = time.perf_counter(), 0, 0
        for _ in range(args.steps):
            action = runner.act(observation)
            predictions += runner.policy.ood_status(0)["new_prediction"]
            observation, _, terminated, truncated, _ = env.step(action)
            steps += 1
            if terminated or truncated:
                observation, _ = env.reset(seed=steps)
                runner.reset()
        elapsed = time.perf_counter() - start
        env.close()
    result = {
        "benchmark": "closed_loop",
        "members": args.members,
        "samples_per_member": runner.policy.config.uncertainty_samples_per_member,
        "vision_backbone_stages": runner.policy.config.vision_backbone_stages,
        "prior_scale": runner.policy.config.prior_scale,
        "torch_threads": args.threads,
        "image_px": env_kwargs_for_policy(runner.policy.config).get("image_size"),
        "inference": f"{runner.policy.config.noise_scheduler_type}-{runner.policy.config.num_inference_steps}",
        "n_action_steps": runner.policy.config.n_action_steps,
        "control_steps": steps,
        "predictions": predictions,
        "control_steps_per_s": round(steps / elapsed, 2),
        "bar_10_hz": steps / elapsed >= 10.0,
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
