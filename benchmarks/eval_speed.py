"""`lerobot-eval` throughput on the suture env: episodes per minute, sync and async, batch sizes 1 and 2.

Prints JSON. The real command runs on an untrained policy of the demo's size (2 members, 32 px, DDIM with
5 steps, normalized with the scripted expert's statistics, so its actions are in metres). An untrained
policy never finishes a throw, so every episode runs the full `episode_length` steps: the work per episode
is the same in every configuration. Videos are written as `lerobot-eval` writes them (the first 10
episodes).

Two rates per configuration: `episodes_per_min` from LeRobot's own `eval_s` (the rollouts), and
`episodes_per_min_wall` from the command's wall time (start-up, worker spawn and model load included).
Time it with nothing else running. On a 2-core machine, async with 2 workers should not be slower than sync.

    python benchmarks/eval_speed.py [--n_episodes=8] [--episode_length=100]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import torch  # noqa: E402
from _policy_builders import save_untrained_expert_policy  # noqa: E402

# The demo's toy ensemble (lerobot_suture/pipelines/demo.py): 2 members, 32 px, a two-level U-Net, DDIM with 5 steps.
DEMO_POLICY = {
    "n_members": 2,
    "noise_scheduler_type": "DDIM",
    "prediction_type": "sample",
    "num_train_timesteps": 20,
    "num_inference_steps": 5,
}
CONFIGURATIONS = [(1, False), (2, False), (2, True)]


def demo_sized_policy(directory: Path) -> Path:
    return save_untrained_expert_policy(directory, **DEMO_POLICY)


def run_eval(
    policy_dir: Path, out: Path, batch_size: int, use_async: bool, n_episodes: int, length: int
) -> dict:
    command = [
        str(Path(sys.executable).parent / "lerobot-eval"),
        f"--policy.path={policy_dir}",
        "--policy.device=cpu",
        "--env.type=suture",
        f"--env.episode_length={length}",
        f"--eval.n_episodes={n_episodes}",
        f"--eval.batch_size={batch_size}",
        f"--eval.use_async_envs={str(use_async).lower()}",
        f"--output_dir={out}",
    ]
    start = time.perf_counter()
    result = subprocess.run(
        command, env={**os.environ, "HF_HUB_OFFLINE": "1"}, capture_output=True, text=True
    )
    wall = time.perf_counter() - start
    if result.returncode != 0:
        raise RuntimeError((result.stdout + result.stderr)[-4000:])
    info = json.loads((out / "eval_info.json").read_text())["overall"]
    assert info["n_episodes"] == n_episodes
    return {
        "batch_size": batch_size,
        "async": use_async,
        "episodes": n_episodes,
        "episodes_per_min": round(60.0 * n_episodes / info["eval_s"], 2),
        "episodes_per_min_wall": round(60.0 * n_episodes / wall, 2),
        "eval_s": round(info["eval_s"], 1),
        "wall_s": round(wall, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n_episodes", type=int, default=8)
    parser.add_argument("--episode_length", type=int, default=100)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        policy_dir = demo_sized_policy(Path(tmp) / "policy")
        runs = []
        for batch_size, use_async in CONFIGURATIONS:
            name = f"b{batch_size}_{'async' if use_async else 'sync'}"
            print(f"lerobot-eval {name} ...", file=sys.stderr, flush=True)
            runs.append(
                run_eval(
                    policy_dir,
                    Path(tmp) / name,
                    batch_size,
                    use_async,
                    args.n_episodes,
                    args.episode_length,
                )
            )
    sync2 = next(r for r in runs if r["batch_size"] == 2 and not r["async"])
    async2 = next(r for r in runs if r["batch_size"] == 2 and r["async"])
    print(
        json.dumps(
            {
                "benchmark": "eval_speed",
                "policy": "untrained, demo-sized ensemble (2 members, 32 px, DDIM 5 steps)",
                "episode_length": args.episode_length,
                "runs": runs,
                "async2_over_sync2": round(async2["episodes_per_min"] / sync2["episodes_per_min"], 2),
                "async2_not_slower_than_sync2": async2["episodes_per_min"] >= sync2["episodes_per_min"],
                "cpu_count": os.cpu_count(),
                "machine": platform.machine(),
                "python": platform.python_version(),
                "torch": torch.__version__,
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
