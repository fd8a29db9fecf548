"""The task family through Gymnasium and LeRobot: every task registered with its episode length, passing
Gymnasium's checker, named by LeRobot's `--env.task`, stepping in async workers, and run by the real
`lerobot-eval` with async envs."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from lerobot.envs.factory import make_env
from lerobot.utils.import_utils import register_third_party_plugins

from lerobot_suture.registration import ENV_ID
from lerobot_suture.sim.suture_env import SutureEnv
from lerobot_suture.sim.tasks import TASK_NAMES, TASKS

register_third_party_plugins()
from lerobot_env_suture import SutureEnvConfig  # noqa: E402

NEW_TASKS = [name for name in TASK_NAMES if name != "insertion"]


@pytest.mark.parametrize("task", TASK_NAMES)
def test_every_task_is_registered_with_its_episode_length_and_its_instruction(task):
    spec = TASKS[task]
    assert gym.spec(spec.gym_id).max_episode_steps == spec.max_episode_steps
    env = gym.make(spec.gym_id, obs_type="state", disable_env_checker=True)
    assert env.unwrapped.task_name == task and env.unwrapped.task_description == spec.instruction
    # Another task's id would cut its episodes at that id's length: refused, naming the task's own id.
    if task == "insertion":
        assert (
            gym.make(ENV_ID, task=task, obs_type="state", disable_env_checker=True).unwrapped.task_name
            == task
        )
    else:
        with pytest.raises(ValueError, match=re.escape(f"gym.make('{spec.gym_id}')")):
            gym.make(ENV_ID, task=task, obs_type="state", disable_env_checker=True)


def test_an_unknown_task_or_a_scenario_a_task_lacks_is_refused_with_the_choices():
    with pytest.raises(ValueError, match="`task` must be one of"):
        SutureEnv(task="knot_tying")
    with pytest.raises(ValueError, match="does not apply to task 'pickup'"):
        SutureEnv(task="pickup", scenario="phantom_moved_after_insertion")
    with pytest.raises(ValueError, match="`task` must be one of"):
        SutureEnvConfig(task="knot_tying")


@pytest.mark.parametrize("obs_type", ["state", "pixels_agent_pos"])
@pytest.mark.parametrize("task", NEW_TASKS)
def test_every_new_task_passes_gymnasium_s_checker(task, obs_type):
    env = SutureEnv(obs_type=obs_type, image_size=32, render_size=32, task=task)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the checker warns about unbounded observation boxes
        check_env(env, skip_render_check=False)
    env.close()


@pytest.mark.parametrize("task", NEW_TASKS)
def test_lerobot_s_env_type_runs_the_task_in_async_workers(task):
    cfg = SutureEnvConfig(task=task, image_size=32, render_size=32)
    assert cfg.gym_id == TASKS[task].gym_id and cfg.episode_length == TASKS[task].max_episode_steps
    assert SutureEnvConfig(task="NeedleInsertion-v0").task == "insertion"  # the older name still reads
    vec = make_env(SutureEnvConfig(task=task, image_size=32, render_size=32, episode_length=3), 2, True)[
        "suture"
    ][0]
    try:
        instruction = TASKS[task].instruction
        assert vec.call("task_description") == (instruction, instruction)
        obs, _ = vec.reset(seed=[0, 1])
        for _ in range(3):
            obs, _, _, truncated, info = vec.step(obs["agent_pos"].astype(np.float32))
        assert truncated.all() and "is_success" in info["final_info"]
    finally:
        vec.close()


def test_a_vector_env_stacks_success_where_one_env_finishes_before_the_other():
    """lerobot-eval stacks ``final_info["is_success"]`` of every env at the step one finishes: the env reports
    Python bools, so the env still running reads False there, not None."""
    from lerobot_suture.expert import ScriptedExpert
    from lerobot_suture.sim.geometry import pose_vector

    make = [lambda: gym.make(TASKS["extraction"].gym_id, image_size=32)] * 2
    envs = gym.vector.SyncVectorEnv(make, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)  # as LeRobot's
    try:
        envs.reset(seed=[3, 4])
        expert, first = ScriptedExpert(), envs.envs[0]
        expert.reset(first)
        for _ in range(TASKS["extraction"].max_episode_steps):
            hold = pose_vector(*envs.envs[1].unwrapped.jaw_pose(), 1.0)  # the second arm holds still
            _, _, terminated, _, info = envs.step(np.stack([expert.act(first), hold]))
            if terminated.any():
                break
        assert terminated.tolist() == [True, False]
        assert info["final_info"]["is_success"].dtype == bool
        assert info["final_info"]["is_success"].tolist() == [True, False]
    finally:
        envs.close()


@pytest.mark.parametrize(
    "task", [pytest.param(t, marks=[] if t == "running_suture" else pytest.mark.slow) for t in NEW_TASKS]
)
def test_lerobot_eval_runs_the_task_with_async_envs(task, tiny_policy_dir, tmp_path):
    """The real `lerobot-eval --env.task=...`, two envs in async workers, as a many-core machine runs it (the
    running suture in the default run, the other tasks in the slow one)."""
    out = tmp_path / "eval"
    result = subprocess.run(
        [
            str(Path(sys.executable).parent / "lerobot-eval"),
            f"--policy.path={tiny_policy_dir}",
            "--policy.device=cpu",
            "--env.type=suture",
            f"--env.task={task}",
            "--env.image_size=32",
            "--env.episode_length=4",
            "--eval.n_episodes=2",
            "--eval.batch_size=2",
            "--eval.use_async_envs=true",
            f"--output_dir={out}",
        ],
        env={**os.environ, "HF_HUB_OFFLINE": "1"},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, (result.stdout + result.stderr)[-4000:]
    metrics = json.loads((out / "eval_info.json").read_text())["per_task"][0]["metrics"]
    assert len(metrics["successes"]) == 2


@pytest.mark.parametrize("task", NEW_TASKS)
def test_a_task_records_as_a_lerobot_dataset_and_calibrates_on_its_own_task(task, tmp_path):
    """The expert's episodes of a task record as a LeRobotDataset with the task's instruction, a card that
    names it, and an episode log from which calibration takes the task."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_suture.datasets.record import record
    from lerobot_suture.datasets.record_config import RecordConfig
    from lerobot_suture.datasets.video import resolve_video_backend
    from lerobot_suture.runtime.calibration import dataset_task

    root = tmp_path / task
    cfg = RecordConfig(
        repo_id=f"suture-tests/{task}",
        root=str(root),
        task=task,
        num_episodes=2,
        val_fraction=0.0,
        image_size=32,
        obs_type="pixels_agent_pos",
    )
    record(cfg)
    ds = LeRobotDataset(f"suture-tests/{task}", root=root, video_backend=resolve_video_backend())
    assert ds.num_episodes == 2
    assert ds[0]["task"] == ds[len(ds) - 1]["task"] == TASKS[task].instruction
    card = (root / "README.md").read_text()
    what = "running suture" if task == "running_suture" else f"needle {task}"
    assert f"robotic {what}**" in card and f"Task `{task}`:" in card
    assert dataset_task(root) == {"task": task}
