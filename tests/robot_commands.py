"""LeRobot's console scripts as the robot-path tests run them: headless, offline, one thread."""

import json
import os
import subprocess
import sys
from pathlib import Path

from lerobot.datasets import LeRobotDataset

from lerobot_suture.datasets.video import resolve_video_backend
from lerobot_suture.sim.task import TASK

BIN = Path(sys.executable).parent
SEED = 40
REPLAY_TOLERANCE_M = 0.5e-3


def environ() -> dict:
    environ = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    return {
        **environ,
        "HF_HUB_OFFLINE": "1",
        "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
        "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "egl"),
        "OMP_NUM_THREADS": "1",
        # Scripted teleoperators: pynput's and SDL's backends that need no display.
        "PYNPUT_BACKEND": "dummy",
        "SDL_VIDEODRIVER": "dummy",
        "SDL_AUDIODRIVER": "dummy",
    }  # and no display: LeRobot reads keys from the terminal, if any


def run_command(name: str, args: list[str], timeout: int = 300) -> str:
    """Run LeRobot's console script ``name`` with ``args``; returns its log, failing on a non-zero exit."""
    result = subprocess.run(
        [str(BIN / name), *args],
        env=environ(),
        stdin=subprocess.DEVNULL,  # no terminal: LeRobot's keyboard controls stay off
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    log = result.stdout + result.stderr
    assert result.returncode == 0, log[-6000:]
    return log


def read_trace(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def load_dataset(root: Path, repo_id: str) -> LeRobotDataset:
    return LeRobotDataset(repo_id, root=root, video_backend=resolve_video_backend())


def episode_frames(dataset: LeRobotDataset, episode: int) -> list[dict]:
    start = int(dataset.meta.episodes["dataset_from_index"][episode])
    stop = int(dataset.meta.episodes["dataset_to_index"][episode])
    return [dataset[i] for i in range(start, stop)]


def robot_args(trace: Path, *extra: str) -> list[str]:
    return ["--robot.type=suture_sim", f"--robot.trace_path={trace}", *extra]


def base_rollout(policy_dir: Path, trace: Path, *robot_extra: str) -> list[dict]:
    """1.5 s of ``lerobot-rollout --strategy.type=base`` of the policy at ``policy_dir`` on the simulated arm
    (``robot_extra``: its further ``--robot.*`` flags); the robot's trace."""
    run_command(
        "lerobot-rollout",
        [
            "--strategy.type=base",
            f"--policy.path={policy_dir}",
            "--device=cpu",
            "--fps=10",
            "--duration=1.5",
            "--return_to_initial_position=false",
            "--play_sounds=false",
            f"--task={TASK}",
            *robot_args(trace, *robot_extra),
        ],
    )
    return read_trace(trace)


def dataset_args(root: Path, repo_id: str, episodes: int, episode_s: float, reset_s: float) -> list[str]:
    return [
        f"--dataset.repo_id={repo_id}",
        f"--dataset.root={root}",
        "--dataset.fps=10",
        f"--dataset.num_episodes={episodes}",
        f"--dataset.episode_time_s={episode_s}",
        f"--dataset.reset_time_s={reset_s}",
        f"--dataset.single_task={TASK}",
        "--dataset.push_to_hub=false",
        "--dataset.no_stamp=true",
        "--play_sounds=false",
        "--display_data=false",
    ]
