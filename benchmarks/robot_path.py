"""The simulated arm on LeRobot's robot path against ``lerobot-eval``, and the real-time loop's period under
either of LeRobot's inference engines.

Three figures, each from LeRobot's own console scripts on the same policy:

1. **Rollout matches eval.** ``lerobot-eval --env.type=suture`` on ``--episodes`` seeds from ``--seed``,
   and ``lerobot-rollout --strategy.type=episodic --robot.type=suture_sim`` on the same seeds (dataset
   episode N plays the scene of ``seed + N``) with the as-fast-as-possible clock and
   ``--robot.episode_end=hold`` (the arm stops at its episode's end, as ``lerobot-eval`` stops an env).
   The rollout's outcome per seed is read from the robot's trace (the step where the throw ended, or the
   env's 10 s limit came). The episodic strategy, not ``base``, because it resets the policy between
   episodes, as ``lerobot-eval`` does; ``base`` runs one continuous scene.
2. **Real time holds, with the gate and the CBF on.** For each engine of ``--engines`` (``sync``: LeRobot's
   inline inference; ``rtc``: its real-time chunking engine, ``--inference.type=rtc``, which predicts the next
   chunk in a background thread), ``lerobot-rollout --strategy.type=gated_dagger`` (the gate, the ``suture_cbf``
   step, the scripted surgeon after a handover) with the real-time clock at 10 Hz for ``--realtime-s``
   seconds, one scene after another: the period between executed control steps (p50, p99, max), and the
   shares over 110 ms and 150 ms. The periods that span the end of a scene (the episode's save and the next
   scene's reset) are left out and counted.
3. **The engines end the same way.** With ``--episodes`` > 0, both engines on the same seeds under the same
   real-time loop, nominal (``--episodes``) and in each of the paper's scenarios (``--scenario-episodes``):
   per seed, success and the frame at which the gate handed over; and the time from the policy's gate
   flagging to the handover. A scenario whose command fails is reported with its error; the others still run.

The real-time engine starts a prediction when its queue holds ``--queue-threshold`` actions or fewer (LeRobot's
``--inference.queue_threshold``, default 30: longer than the reference's chunk, so it predicts back to back and
each action comes from the freshest chunk; the policy's ``n_action_steps`` predicts as often as the sync engine).

``--untrained-preset FILE`` times a policy of that preset's architecture with untrained weights (its
needle target off, a training-only head) instead of ``--policy-path``: periods only, since an untrained
policy's outcomes mean nothing; part 1 and 3 are skipped.

Prints one JSON object (and writes it to ``--out`` when given, after every stage)::

    .venv/bin/python benchmarks/robot_path.py --policy-path DIR [--episodes 50] [--seed 2000000]
    .venv/bin/python benchmarks/robot_path.py --untrained-preset policies/presets/reference.json --realtime-s 600
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

import numpy as np
from _report import emit, write

from lerobot_suture.plotting import save_figure

NEEDS = "a trained policy (--policy-path), or a preset to time untrained (--untrained-preset)"
BIN = Path(sys.executable).parent
CONTROL_PERIOD_S = 0.1
LATE_FACTOR = 1.1
VERY_LATE_FACTOR = 1.5
ENGINES = ("sync", "rtc")
PARTS = ("consistency", "realtime", "outcomes")
SCENARIOS = ("nominal", "needle_drop", "camera_moved", "phantom_servo", "phantom_moved_after_insertion")
"""The paper's scenarios (``lerobot_suture.sim.scenarios.SCENARIOS``)."""
TASK = "Insert the curved suture needle at the entry point and drive it out through the exit point."


def _environ() -> dict:
    return {
        **os.environ,
        "HF_HUB_OFFLINE": "1",
        "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
        "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "egl"),
    }


def _run(name: str, args: list[str], log: Path) -> float:
    """Run a LeRobot console script; returns its wall time (s). Its output goes to ``log``."""
    start = time.perf_counter()
    with log.open("w") as out:
        result = subprocess.run(
            [str(BIN / name), *args], env=_environ(), stdin=subprocess.DEVNULL, stdout=out, stderr=out
        )
    if result.returncode != 0:
        raise RuntimeError(f"{name} failed (exit {result.returncode}); its log: {log}")
    return time.perf_counter() - start


def _image_size(policy_path: Path) -> int:
    config = json.loads((policy_path / "config.json").read_text())
    shape = config["input_features"]["observation.images.endoscope"]["shape"]
    return int(shape[-1])


def eval_outcomes(policy_path: Path, episodes: int, seed: int, work: Path) -> tuple[dict[int, bool], float]:
    out = work / "eval"
    seconds = _run(
        "lerobot-eval",
        [
            f"--policy.path={policy_path}",
            "--env.type=suture",
            f"--eval.n_episodes={episodes}",
            "--eval.batch_size=1",
            f"--seed={seed}",
            "--policy.device=cpu",
            f"--output_dir={out}",
        ],
        work / "eval.log",
    )
    successes = json.loads((out / "eval_info.json").read_text())["per_task"][0]["metrics"]["successes"]
    # One env: lerobot-eval seeds episode i with seed + i.
    return {seed + i: bool(success) for i, success in enumerate(successes)}, seconds


def trace_outcomes(trace: list[dict]) -> dict[int, bool | None]:
    """Per scene seed: the outcome at the step its episode ended (None: it never ended)."""
    outcomes: dict[int, bool | None] = {}
    for line in trace:
        seed = int(line["seed"])
        if outcomes.get(seed) is not None:
            continue
        ended = line["throw_over"] or line.get("time_limit", False)
        outcomes[seed] = bool(line["is_success"]) if ended else None
    return outcomes


def rollout_outcomes(
    policy_path: Path, episodes: int, seed: int, episode_s: float, work: Path
) -> tuple[dict[int, bool | None], float]:
    trace = work / "rollout_trace.jsonl"
    seconds = _run(
        "lerobot-rollout",
        [
            "--strategy.type=episodic",
            f"--policy.path={policy_path}",
            "--device=cpu",
            "--fps=50",  # the loop's pace; the fast clock never waits, the held arm ends each scene
            "--return_to_initial_position=false",
            "--robot.type=suture_sim",
            f"--robot.seed={seed}",
            f"--robot.image_size={_image_size(policy_path)}",
            "--robot.clock=fast",
            "--robot.episode_end=hold",
            f"--robot.trace_path={trace}",
            "--dataset.repo_id=local/rollout_robot_path_benchmark",
            f"--dataset.root={work / 'rollout_dataset'}",
            "--dataset.fps=10",
            f"--dataset.num_episodes={episodes}",
            f"--dataset.episode_time_s={episode_s}",
            "--dataset.reset_time_s=0",
            "--dataset.single_task=Insert the curved suture needle at the entry point and drive it out "
            "through the exit point.",
            "--dataset.push_to_hub=false",
            "--play_sounds=false",
            "--display_data=false",
        ],
        work / "rollout.log",
    )
    lines = [json.loads(line) for line in trace.read_text().splitlines()]
    return trace_outcomes(lines), seconds


def gated_rollout(
    policy_path: Path,
    engine: str,
    work: Path,
    *,
    seed: int,
    episodes: int,
    episode_s: float,
    duration: float,
    scenario: str = "nominal",
    queue_threshold: int | None = None,
    calibration_file: str | None = None,
) -> tuple[list[dict], Path]:
    """``lerobot-rollout --strategy.type=gated_dagger`` on the real-time clock at 10 Hz under ``engine``; returns
    the robot's trace and the recorded dataset's root. ``calibration_file``: the gate's, in the policy directory
    (unset: the policy's own; absent: the gate reports and never hands over)."""
    work.mkdir(parents=True, exist_ok=True)
    trace, root = work / f"{engine}_trace.jsonl", work / f"{engine}_dataset"
    args = [
        "--strategy.type=gated_dagger",
        f"--inference.type={engine}",
        f"--policy.path={policy_path}",
        "--teleop.type=suture_scripted",
        "--device=cpu",
        "--fps=10",
        "--return_to_initial_position=false",
        "--robot.type=suture_sim",
        f"--robot.seed={seed}",
        f"--robot.image_size={_image_size(policy_path)}",
        f"--robot.scenario={scenario}",
        "--robot.clock=realtime",
        "--robot.episode_end=hold",
        "--robot.tip_tracking=true",
        "--robot.registration=true",
        f"--robot.trace_path={trace}",
        f"--dataset.repo_id=local/rollout_robot_path_{engine}",
        f"--dataset.root={root}",
        "--dataset.fps=10",
        f"--dataset.num_episodes={episodes}",
        f"--dataset.episode_time_s={episode_s}",
        "--dataset.reset_time_s=0",
        f"--dataset.single_task={TASK}",
        "--dataset.push_to_hub=false",
        "--play_sounds=false",
        "--display_data=false",
    ]
    if duration > 0:
        args.append(f"--duration={duration}")
    if engine == "rtc" and queue_threshold is not None:
        args.append(f"--inference.queue_threshold={queue_threshold}")
    if calibration_file is not None:
        args.append(f"--policy.ood.calibration_file={calibration_file}")
    _run("lerobot-rollout", args, work / f"{engine}.log")
    return [json.loads(line) for line in trace.read_text().splitlines()], root


def flag_to_handover_ms(log: Path) -> list[float]:
    """Per handover by the policy's gate in ``log``: milliseconds from the gate's flag to the handover."""
    pattern = re.compile(r"handing over, ([0-9.]+) ms after the policy's gate flagged")
    return [float(m.group(1)) for m in pattern.finditer(log.read_text())]


def scene_periods(trace: list[dict]) -> tuple[np.ndarray, int]:
    """The periods (s) between executed control steps of the same scene, and how many scene boundaries (an
    episode's save and the next scene's reset) were left out, from the robot's trace."""
    times = np.array([line["wall_time"] for line in trace])
    seeds = np.array([line["seed"] for line in trace])
    same_scene = seeds[1:] == seeds[:-1]
    return np.diff(times)[same_scene], int((~same_scene).sum())


def period_report(trace: list[dict]) -> dict:
    """The distribution of :func:`scene_periods`."""
    periods, boundaries = scene_periods(trace)
    seeds = {line["seed"] for line in trace}
    return {
        "steps": len(trace),
        "scenes": len(seeds),
        "scene_boundaries_left_out": boundaries,
        "period_s": {
            "p50": round(float(np.percentile(periods, 50)), 4),
            "p99": round(float(np.percentile(periods, 99)), 4),
            "max": round(float(periods.max()), 4),
            "mean": round(float(periods.mean()), 4),
        },
        "late_share": round(float(np.mean(periods > LATE_FACTOR * CONTROL_PERIOD_S)), 5),
        "over_150ms_share": round(float(np.mean(periods > VERY_LATE_FACTOR * CONTROL_PERIOD_S)), 5),
        "rate_hz": round(float(1.0 / periods.mean()), 3),
        "holds_10_hz": bool(np.percentile(periods, 99) <= LATE_FACTOR * CONTROL_PERIOD_S),
    }


def plot_periods(traces: dict[str, list[dict]], path: Path) -> None:
    """A histogram of each engine's periods, with the 110 ms and 150 ms marks, to ``path`` (PNG)."""
    from matplotlib.figure import Figure

    figure = Figure(figsize=(7, 3.2), dpi=120)
    axes = figure.add_subplot()
    bins = np.linspace(0.0, 0.35, 71)
    for engine, trace in traces.items():
        periods, _ = scene_periods(trace)
        axes.hist(
            np.clip(periods, 0.0, 0.35), bins=bins, alpha=0.6, label=f"{engine} ({periods.size} periods)"
        )
    for mark in (LATE_FACTOR, VERY_LATE_FACTOR):
        axes.axvline(mark * CONTROL_PERIOD_S, color="k", linestyle="--", linewidth=0.8)
    axes.set_yscale("log")
    axes.set_xlabel("period between executed control steps (s); dashed: 110 ms and 150 ms")
    axes.set_ylabel("periods")
    axes.set_title("lerobot-rollout at 10 Hz, gate and CBF on: sync against real-time chunking", fontsize=10)
    axes.legend()
    figure.tight_layout()
    save_figure(figure, path)


def gated_outcomes(trace: list[dict], root: Path, repo_id: str) -> dict[int, dict]:
    """Per scene seed: success at the scene's end, and the frame at which the gate handed over (None: never)."""
    from lerobot.datasets import LeRobotDataset

    dataset = LeRobotDataset(repo_id, root=root)
    episode_seeds = list(dict.fromkeys(line["seed"] for line in trace))
    outcomes = {}
    for episode, seed in enumerate(episode_seeds[: dataset.meta.total_episodes]):
        start = int(dataset.meta.episodes["dataset_from_index"][episode])
        stop = int(dataset.meta.episodes["dataset_to_index"][episode])
        intervention = [bool(dataset.hf_dataset[i]["intervention"]) for i in range(start, stop)]
        last = [line for line in trace if line["seed"] == seed][-1]
        outcomes[int(seed)] = {
            "success": bool(last["is_success"]),
            "handover": intervention.index(True) if any(intervention) else None,
        }
    return outcomes


def compare_engines(sync: dict[int, dict], rtc: dict[int, dict]) -> dict:
    """How often the engines end the same way, and how far apart their handovers fall (frames; > 0: RTC later)."""
    seeds = sorted(set(sync) & set(rtc))
    engines = {"sync": sync, "rtc": rtc}
    same = [s for s in seeds if sync[s]["success"] == rtc[s]["success"]]
    both = [s for s in seeds if sync[s]["handover"] is not None and rtc[s]["handover"] is not None]
    return {
        "seeds": len(seeds),
        "same_ending": len(same),
        "handover_only_one_engine": sum(
            (sync[s]["handover"] is None) != (rtc[s]["handover"] is None) for s in seeds
        ),
        "handover_shift_frames": [rtc[s]["handover"] - sync[s]["handover"] for s in both],
        "handovers": {name: sum(o[s]["handover"] is not None for s in seeds) for name, o in engines.items()},
        "successes": {name: sum(o[s]["success"] for s in seeds) for name, o in engines.items()},
    }


def untrained_policy(preset: Path, directory: Path) -> Path:
    """A policy of ``preset``'s architecture with untrained weights, normalized with the expert's statistics."""
    from _policy_builders import save_untrained_expert_policy

    fields = json.loads(preset.read_text())["policy"]
    fields = {
        k: tuple(v) if isinstance(v, list) else v
        for k, v in fields.items()
        if k not in ("type", "device", "push_to_hub")
    }
    fields["needle_keypoints_weight"] = 0.0  # a training-only head; inference is the same without it
    return save_untrained_expert_policy(directory, **fields)


def consistency(policy_path: Path, args, work: Path) -> dict:
    """Part 1: the episodic rollout's outcomes against ``lerobot-eval``'s on the same seeds."""
    from lerobot_suture.experiments.metrics import wilson_interval

    evaluated, eval_s = eval_outcomes(policy_path, args.episodes, args.seed, work)
    rolled, rollout_s = rollout_outcomes(policy_path, args.episodes, args.seed, args.episode_s, work)
    seeds = [args.seed + k for k in range(args.episodes)]
    eval_successes = sum(evaluated[s] for s in seeds)
    finished = [s for s in seeds if rolled.get(s) is not None]
    rollout_successes = sum(bool(rolled[s]) for s in finished)
    low, high = (round(b, 6) for b in wilson_interval(eval_successes, len(seeds)))
    rollout_rate = rollout_successes / len(seeds)
    return {
        "eval": {
            "successes": eval_successes,
            "success_rate": eval_successes / len(seeds),
            "wilson95": [low, high],
            "seconds": round(eval_s, 1),
        },
        "rollout": {
            "successes": rollout_successes,
            "success_rate": rollout_rate,
            "wilson95": [round(b, 6) for b in wilson_interval(rollout_successes, len(seeds))],
            "unfinished_episodes": len(seeds) - len(finished),
            "seconds": round(rollout_s, 1),
        },
        "same_outcome_share": sum(evaluated[s] == rolled.get(s) for s in seeds) / len(seeds),
        "rollout_within_eval_interval": bool(low <= rollout_rate <= high),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--policy-path", type=Path)
    source.add_argument("--untrained-preset", type=Path, help="time this preset's architecture, untrained")
    parser.add_argument("--engines", default=",".join(ENGINES), help="comma-separated, of sync and rtc")
    parser.add_argument("--episodes", type=int, default=50, help="0: periods only")
    parser.add_argument("--scenario-episodes", type=int, default=10, help="per scenario, for the engines")
    parser.add_argument("--seed", type=int, default=2_000_000, help="first test seed (the experiments')")
    parser.add_argument("--episode-s", type=float, default=20.0, help="wall time of a rollout episode")
    parser.add_argument("--realtime-s", type=float, default=600.0, help="each engine's real-time run")
    parser.add_argument("--out", type=Path)
    parser.add_argument(
        "--parts",
        default=",".join(PARTS),
        help=f"comma-separated, of {', '.join(PARTS)} (the three figures above)",
    )
    parser.add_argument("--queue-threshold", type=int, help="the real-time engine's (default: LeRobot's, 30)")
    parser.add_argument("--plot", type=Path, help="a PNG of the real-time periods, per engine")
    parser.add_argument(
        "--work-dir", type=Path, help="the commands' outputs and logs (default: a new temp dir)"
    )
    args = parser.parse_args()
    engines, parts = args.engines.split(","), args.parts.split(",")
    if not set(engines) <= set(ENGINES):
        raise SystemExit(f"--engines must name some of {ENGINES}; got {args.engines!r}.")
    if not set(parts) <= set(PARTS):
        raise SystemExit(f"--parts must name some of {PARTS}; got {args.parts!r}.")
    work = args.work_dir or Path(tempfile.mkdtemp(prefix="robot_path_"))
    if work.exists() and any(work.iterdir()):
        raise SystemExit(f"--work-dir {work} is not empty: the commands' outputs would mix; pass a new one.")
    work.mkdir(parents=True, exist_ok=True)
    policy_path = args.policy_path or untrained_policy(args.untrained_preset, work / "untrained_policy")
    trained = args.policy_path is not None
    rollout = partial(gated_rollout, policy_path, queue_threshold=args.queue_threshold, seed=args.seed)
    result: dict = {
        "command": " ".join(["python", *sys.argv]),
        "policy_path": str(args.policy_path)
        if trained
        else f"untrained, architecture of {args.untrained_preset}",
        "episodes": args.episodes if trained else 0,
        "first_seed": args.seed,
        "queue_threshold": args.queue_threshold,
    }

    def save() -> None:
        if args.out is not None:
            write(result, args.out)

    if trained and args.episodes > 0 and "consistency" in parts:
        result.update(consistency(policy_path, args, work))
        save()
    result["realtime"], traces = {}, {}
    for engine in engines if "realtime" in parts else ():
        start = time.perf_counter()
        trace, _ = rollout(
            engine, work / "realtime", episodes=100_000, episode_s=60.0, duration=args.realtime_s
        )
        traces[engine] = trace
        result["realtime"][engine] = {
            **period_report(trace),
            "seconds": round(time.perf_counter() - start, 1),
        }
        save()
    if args.plot is not None and traces:
        plot_periods(traces, args.plot)
    if trained and args.episodes > 0 and len(engines) == 2 and "outcomes" in parts:
        # Nominal on --episodes seeds, and each of the paper's scenarios on --scenario-episodes.
        runs = {"nominal": args.episodes, **{name: args.scenario_episodes for name in SCENARIOS[1:]}}
        runs = {name: episodes for name, episodes in runs.items() if episodes > 0}
        result["engines_compared"], delays = {}, {engine: [] for engine in engines}
        for scenario, episodes in runs.items():
            outcomes, run_dir = {}, work / "outcomes" / scenario
            try:
                for engine in engines:
                    trace, root = rollout(
                        engine,
                        run_dir,
                        episodes=episodes,
                        episode_s=args.episode_s,
                        duration=0,
                        scenario=scenario,
                    )
                    outcomes[engine] = gated_outcomes(trace, root, f"local/rollout_robot_path_{engine}")
                    delays[engine] += flag_to_handover_ms(run_dir / f"{engine}.log")
            except RuntimeError as error:  # one scenario's failed command leaves the others' figures
                result.setdefault("engines_compared_failed", {})[scenario] = str(error)
                continue
            result["engines_compared"][scenario] = compare_engines(outcomes["sync"], outcomes["rtc"])
            result["flag_to_handover_ms"] = {
                engine: {"handovers": len(d), "max": round(max(d), 1) if d else None}
                for engine, d in delays.items()
            }
            save()
    result["work_dir"] = str(work)
    result["machine"] = {
        "cpus": os.cpu_count(),
        "platform": platform.platform(),
        "load_at_end": os.getloadavg(),
    }
    emit(result, args.out)


if __name__ == "__main__":
    main()
