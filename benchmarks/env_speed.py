"""Env speed on one core: control steps/s without and with the endoscope image, ms per frame, for one task.

Prints JSON. Targets: >= 1,000 steps/s without images, >= 500 steps/s with the 96 px image.
Actions are an expert episode's, recorded once and replayed, so only the env is timed.

    python benchmarks/env_speed.py [--task insertion|pickup|extraction|running_suture]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

import lerobot_suture  # noqa: E402,F401
from lerobot_suture.expert import ScriptedExpert  # noqa: E402
from lerobot_suture.sim.suture_env import SutureEnv  # noqa: E402
from lerobot_suture.sim.tasks import TASK_NAMES  # noqa: E402

N_STEPS = 3000


def expert_actions(task: str, seed: int = 0) -> list[np.ndarray]:
    env, expert = SutureEnv(obs_type="state", task=task), ScriptedExpert()
    env.reset(seed=seed)
    expert.reset(env)
    actions, done = [], False
    while not done:
        actions.append(expert.act(env))
        done = env.step(actions[-1])[2] or len(actions) >= env.task_spec.max_episode_steps
    return actions


def steps_per_second(task: str, obs_type: str, image_size: int, actions: list[np.ndarray]) -> float:
    env = SutureEnv(obs_type=obs_type, image_size=image_size, task=task)
    env.reset(seed=0)
    for a in actions[:10]:  # warm up (renderer creation)
        env.step(a)
    env.reset(seed=0)
    k, start = 0, time.perf_counter()
    for step in range(N_STEPS):
        if k == len(actions):
            env.reset(seed=step)
            k = 0
        env.step(actions[k])
        k += 1
    elapsed = time.perf_counter() - start
    env.close()
    return N_STEPS / elapsed


def ms_per_frame(image_size: int) -> float:
    env = SutureEnv(obs_type="pixels_agent_pos", image_size=image_size)
    env.reset(seed=0)
    env._observation()
    start = time.perf_counter()
    for _ in range(1000):
        env._observation()
    return time.perf_counter() - start  # 1000 frames -> seconds == ms per frame


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", choices=TASK_NAMES, default="insertion")
    task = parser.parse_args().task
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})  # one core
    actions = expert_actions(task)
    no_image = steps_per_second(task, "state", 96, actions)
    result = {
        "benchmark": "env_speed",
        "task": task,
        "cores": 1,
        "physics_dt_s": 0.002,
        "control_dt_s": 0.1,
        "steps_per_s_no_image": round(no_image, 1),
        "ms_per_step_no_image": round(1000 / no_image, 3),
    }
    for size in (96, 64):
        with_image = steps_per_second(task, "pixels_agent_pos", size, actions)
        result[f"steps_per_s_endoscope_{size}px"] = round(with_image, 1)
        result[f"ms_per_frame_{size}px"] = round(ms_per_frame(size), 3)
    result["bar_no_image_1000"] = result["steps_per_s_no_image"] >= 1000
    result["bar_endoscope_96px_500"] = result["steps_per_s_endoscope_96px"] >= 500
    result["machine"] = platform.processor() or platform.machine()
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
