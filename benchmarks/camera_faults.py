"""The stale-camera watchdog against a frozen and a dropping endoscope, on scripted-expert insertions.

Per seed the scripted expert drives the insertion env once; each observation goes, as the robot's would
(``{"endoscope": frame, "x.pos": ..., ...}``), through three ``FaultInjector``s, each watched by its own
``CameraWatchdog``:

- nominal: no fault; any flag is a false alarm;
- frozen: the frame frozen from an onset step drawn uniformly from [5, 30] (``np.random.default_rng(seed)``);
  the delay (control steps of 0.1 s) from the onset to the flag, None if never within the episode;
- dropped: frames dropped at ``--drop-rate``; flagged or not, and the delay from the first drop.

The expert plans from the simulator's state, not from the camera, so the three share one trajectory.
Prints one JSON object: episodes, false-alarm episodes, and per fault the episodes flagged within 5 steps
(count, rate, Wilson 95% interval) and the delay's p50 / max. Bar: a frozen frame flagged within 5 steps in
>= 90% of episodes, and 0 false alarms.

    .venv/bin/python benchmarks/camera_faults.py [--episodes 100] [--seed-start 3000000] [--output PATH]

Ctrl-C stops early and still prints what was finished.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
from _report import emit, machine  # noqa: E402
from lerobot_robot_suture.faults import POSE_KEYS, FaultConfig, FaultInjector  # noqa: E402
from tqdm import tqdm  # noqa: E402

from lerobot_suture.experiments.metrics import wilson_interval  # noqa: E402
from lerobot_suture.expert import ScriptedExpert  # noqa: E402
from lerobot_suture.safety.camera_watchdog import CameraWatchdog, CameraWatchdogConfig  # noqa: E402
from lerobot_suture.sim.suture_env import SutureEnv  # noqa: E402

FROZEN_ONSETS = (5, 30)  # control steps, inclusive
WITHIN_STEPS = 5
BAR_RATE = 0.90


@dataclass
class Episode:
    seed: int
    steps: int
    false_alarm: bool
    frozen_onset: int
    frozen_flagged_at: int | None
    first_drop: int | None
    dropped_flagged_at: int | None

    @property
    def frozen_delay(self) -> int | None:
        return None if self.frozen_flagged_at is None else self.frozen_flagged_at - self.frozen_onset

    @property
    def dropped_delay(self) -> int | None:
        if self.dropped_flagged_at is None or self.first_drop is None:
            return None
        return self.dropped_flagged_at - self.first_drop


def run_episode(
    env: SutureEnv, seed: int, drop_rate: float, watchdog_config: CameraWatchdogConfig
) -> Episode:
    onset = int(np.random.default_rng(seed).integers(FROZEN_ONSETS[0], FROZEN_ONSETS[1] + 1))
    injectors = {
        "nominal": FaultInjector(FaultConfig()),
        "frozen": FaultInjector(FaultConfig(frozen_camera_step=onset)),
        "dropped": FaultInjector(FaultConfig(dropped_frame_rate=drop_rate)),
    }
    watchdogs = {name: CameraWatchdog(watchdog_config) for name in injectors}
    for injector in injectors.values():
        injector.reset(seed)
    obs, _ = env.reset(seed=seed)
    expert = ScriptedExpert()
    expert.reset(env)
    steps = 0
    while True:
        measured = {key: float(v) for key, v in zip(POSE_KEYS, obs["agent_pos"], strict=True)}
        measured["endoscope"] = obs["pixels"]["endoscope"]
        for name, injector in injectors.items():
            seen = injector.observe(measured)
            pose = np.array([seen[key] for key in POSE_KEYS])
            watchdogs[name].update(seen["endoscope"], pose)
        obs, _reward, terminated, truncated, _info = env.step(expert.act(env))
        steps += 1
        if terminated or truncated:
            break
    drops = injectors["dropped"].dropped_steps
    return Episode(
        seed=seed,
        steps=steps,
        false_alarm=watchdogs["nominal"].flagged_at is not None,
        frozen_onset=onset,
        frozen_flagged_at=watchdogs["frozen"].flagged_at,
        first_drop=drops[0] if drops else None,
        dropped_flagged_at=watchdogs["dropped"].flagged_at,
    )


def detection(delays: list[int | None], n: int) -> dict:
    """Episodes flagged within ``WITHIN_STEPS`` of the fault's start, and the delay's p50 / max (steps)."""
    within = sum(d is not None and 0 <= d <= WITHIN_STEPS for d in delays)
    found = [d for d in delays if d is not None]
    return {
        "flagged_within_5": within,
        "rate": within / n if n else None,
        "wilson95": [round(b, 4) for b in wilson_interval(within, n)] if n else None,
        "flagged": len(found),
        "delay_steps": {
            "p50": float(np.median(found)) if found else None,
            "max": int(max(found)) if found else None,
        },
    }


def summarize(episodes: list[Episode], drop_rate: float) -> dict:
    n = len(episodes)
    with_drops = [e for e in episodes if e.first_drop is not None]
    frozen = detection([e.frozen_delay for e in episodes], n)
    frozen["flagged_before_onset"] = sum(
        e.frozen_flagged_at is not None and e.frozen_flagged_at < e.frozen_onset for e in episodes
    )
    frozen["onset_range_steps"] = list(FROZEN_ONSETS)
    dropped = detection([e.dropped_delay for e in with_drops], len(with_drops))
    dropped["episodes_with_drops"] = len(with_drops)
    dropped["drop_rate"] = drop_rate
    false_alarms = sum(e.false_alarm for e in episodes)
    return {
        "episodes": n,
        "steps_median": float(np.median([e.steps for e in episodes])) if episodes else None,
        "false_alarm_episodes": false_alarms,
        "frozen": frozen,
        "dropped": dropped,
        "bar": {
            "frozen_within_5_rate_min": BAR_RATE,
            "false_alarm_episodes_max": 0,
            "pass": bool(n and frozen["rate"] >= BAR_RATE and false_alarms == 0),
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed-start", type=int, default=3_000_000)
    parser.add_argument("--image-size", type=int, default=96, help="endoscope image side (px)")
    parser.add_argument("--drop-rate", type=float, default=0.3, help="dropped-frame probability per step")
    parser.add_argument("--output", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args()

    watchdog_config = CameraWatchdogConfig()
    env = SutureEnv(image_size=args.image_size)
    episodes: list[Episode] = []
    seeds = range(args.seed_start, args.seed_start + args.episodes)
    start = time.perf_counter()
    try:
        for seed in tqdm(seeds, desc="camera faults", unit="episode", file=sys.stderr):
            episodes.append(run_episode(env, seed, args.drop_rate, watchdog_config))
    except KeyboardInterrupt:
        print(f"interrupted after {len(episodes)} of {len(seeds)} episodes", file=sys.stderr)
    finally:
        env.close()
    report = {"benchmark": "camera_faults", "first_seed": args.seed_start, "image_size": args.image_size}
    report.update(summarize(episodes, args.drop_rate))
    report["watchdog"] = vars(watchdog_config)
    report["missed_frozen_seeds"] = [
        e.seed for e in episodes if e.frozen_delay is None or not 0 <= e.frozen_delay <= WITHIN_STEPS
    ]
    report["wall_s"] = round(time.perf_counter() - start, 1)
    report["machine"] = machine()
    emit(report, args.output)


if __name__ == "__main__":
    main()
