"""What each observation and data lever does to one task's learned policy: one line per lever, on 50 test seeds.

A lever line records its dataset with the scripted expert (``lerobot-suture record``, the task's recipe),
trains the task's preset with the real ``lerobot-train`` for the preset's steps on the recording's training
episodes, and evaluates the checkpoint (a subtask-conditioned one inside a ``suture_chain``, whose high level
gives it the subtask) on the leaderboard's nominal test seeds of the task (the same scenes
as the board's nominal cell; the CBF on, the gate only reporting). One thing changes from one line to the
next, so that data scale and an added camera are told apart; the training steps stay the preset's.

    .venv/bin/python benchmarks/task_levers.py --task pickup [--members 1] [--output FILE]

Every stage is resumable: a finished recording, training or evaluation is read back, so an interrupted run
goes on where it stopped. Each stage's wall time is reported. ``--figure`` draws each line's success rate
with its Wilson interval. ``--scenarios`` also evaluates each line on the task's perturbation scenarios (the
board's other cells of the task, their own test seeds).
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path

from _report import emit, machine

ROOT = Path(__file__).resolve().parents[1]
NEEDS = "a task to run (--task); records, trains and evaluates each lever (about 30 min a lever on 2 cores)"


@dataclass(frozen=True)
class Lever:
    """One line of the table: the episodes recorded; whether the wrist camera, the wound's marks and the
    high level's subtask and throw are recorded (a policy trained on them reads them); whether the actions
    are relative to the jaw's measured pose (the policy then runs in an env that takes them); how far (m)
    the expert's first regrasp of each extraction misses before it recovers (0: it never misses); the
    noise (m) executed but not recorded while it reaches for a regrasp (DART; 0: none); whether the regrasp
    planned through the marks is recorded as an observation, with the expert's regrasps aimed at it; where the
    evaluation's env plans that regrasp from (``regrasp_from``: ``marks`` or ``release``); the control steps the
    expert holds the open jaw on a regrasp's pose before it closes (``regrasp_settle``); how far (m) its reach
    may end beside the grasp's line, the advance correcting it (``regrasp_reach_offset``); whether the evaluation
    scripts the regrasp (``scripted_regrasp``: the checkpoint inside a ``suture_chain`` whose servo takes the tip,
    the checkpoint pulling); and the lever whose recording and checkpoint a line evaluates instead of its own
    (``checkpoint_of``: one checkpoint, two envs)."""

    name: str
    episodes: int | None  # None: the task recipe's own count
    wrist_camera: bool = False
    marks: bool = False
    subtask: bool = False
    relative_actions: bool = False
    regrasp_miss: float = 0.0
    regrasp_noise: float = 0.0
    regrasp_target: bool = False
    regrasp_from: str = "marks"
    regrasp_settle: int = 0
    regrasp_reach_offset: float = 0.0
    scripted_regrasp: bool = False
    checkpoint_of: str | None = None


LEVERS = (
    Lever("recipe", None),
    Lever("data x500", 500),
    Lever("data x500 + wrist camera", 500, wrist_camera=True),
    Lever("data x500 + marks", 500, marks=True),
    Lever("marks + subtask", None, marks=True, subtask=True),
    Lever("relative actions", None, relative_actions=True),
    Lever("relative actions + wrist camera", None, wrist_camera=True, relative_actions=True),
    Lever("data x500 + relative actions", 500, relative_actions=True),
    Lever("marks + subtask + relative actions", None, marks=True, subtask=True, relative_actions=True),
    Lever("relative actions + missed regrasps recovered", None, relative_actions=True, regrasp_miss=0.001),
    Lever("relative actions + DART regrasps", None, relative_actions=True, regrasp_noise=0.0004),
    Lever("relative actions + planned regrasp", None, relative_actions=True, regrasp_target=True),
    Lever(
        "relative actions + planned regrasp, evaluated with the plan from the release",
        None,
        relative_actions=True,
        regrasp_target=True,
        regrasp_from="release",
        checkpoint_of="relative actions + planned regrasp",
    ),
    Lever(
        "relative actions + regrasp planned from the release",
        None,
        relative_actions=True,
        regrasp_target=True,
        regrasp_from="release",
    ),
    Lever(
        "relative actions + planned regrasp, settled closing",
        None,
        relative_actions=True,
        regrasp_target=True,
        regrasp_settle=3,
    ),
    Lever(
        "relative actions + planned regrasp, settled closing, reach corrected",
        None,
        relative_actions=True,
        regrasp_target=True,
        regrasp_settle=3,
        regrasp_reach_offset=0.001,
    ),
    Lever(
        "relative actions + planned regrasp, the regrasp scripted",
        None,
        relative_actions=True,
        regrasp_target=True,
        scripted_regrasp=True,
        checkpoint_of="relative actions + planned regrasp",
    ),
)


def _run(command: list[str], log: Path) -> float:
    """Run ``command`` with its output appended to ``log``; its wall time (s). A failure names the log."""
    start = time.perf_counter()
    with log.open("a") as out:
        done = subprocess.run(command, stdout=out, stderr=subprocess.STDOUT, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command[:3])} ... exited {done.returncode}; see {log}")
    return time.perf_counter() - start


def record(task: str, lever: Lever, root: Path, log: Path) -> dict:
    """The lever's dataset (resumed if a run was interrupted); its episodes and recording time (s)."""
    from lerobot_suture.leaderboard.pipeline import TASK_RECIPES

    recipe = TASK_RECIPES[task][0]
    info = root / "meta" / "info.json"
    done = root / "recorded.json"
    if done.is_file():
        return json.loads(done.read_text())
    command = [
        str(Path(sys.executable).parent / "lerobot-suture"),
        "record",
        f"--config_path={recipe}",
        f"--root={root}",
        f"--repo_id=local/levers_{task}_{root.name}",
        f"--wrist_camera={str(lever.wrist_camera).lower()}",
        f"--marks={str(lever.marks).lower()}",
        f"--subtask={str(lever.subtask).lower()}",
        f"--relative_actions={str(lever.relative_actions).lower()}",
        f"--resume={str(info.is_file()).lower()}",
    ]
    if lever.episodes is not None:
        command.append(f"--num_episodes={lever.episodes}")
    if lever.regrasp_miss:
        command.append(f"--regrasp_miss={lever.regrasp_miss:g}")
    if lever.regrasp_noise:
        command.append(f"--regrasp_noise={lever.regrasp_noise:g}")
    if lever.regrasp_settle:
        command.append(f"--regrasp_settle={lever.regrasp_settle}")
    if lever.regrasp_reach_offset:
        command.append(f"--regrasp_reach_offset={lever.regrasp_reach_offset:g}")
    if lever.regrasp_target:  # the expert's regrasps go where the plan says
        aim = lever.regrasp_from
        command += ["--regrasp_target=true", f"--regrasp_from={aim}", f"--regrasp_aim={aim}"]
    seconds = _timed(root.parent / f"{root.name}.record_s.json", "record_s", lambda: _run(command, log))
    episodes = json.loads(info.read_text())["total_episodes"]
    result = {"episodes": episodes, "record_s": round(seconds, 1)}
    done.write_text(json.dumps(result))
    return result


def _timed(path: Path, key: str, run) -> float:
    """``run()``'s wall time (s) plus that of the earlier runs it resumes, kept in ``path`` even when it is
    interrupted (SIGTERM included: :func:`main` turns it into an exit), so a resumed stage reports its whole cost."""
    spent = json.loads(path.read_text())[key] if path.is_file() else 0.0
    start = time.perf_counter()
    try:
        run()
    finally:
        spent += time.perf_counter() - start
        path.write_text(json.dumps({key: spent}))
    return spent


def train(task: str, root: Path, out: Path, members: int) -> tuple[Path, float]:
    """``lerobot-train`` of the task's preset on the recording's training episodes (resumable); the
    pretrained directory and the training's wall time (s), summed over the runs that resumed it."""
    from lerobot_suture.datasets.split import train_episodes
    from lerobot_suture.datasets.video import resolve_video_backend
    from lerobot_suture.leaderboard.pipeline import TASK_RECIPES
    from lerobot_suture.runtime.training import run_lerobot_train

    preset = TASK_RECIPES[task][1]
    reference = json.loads(preset.read_text())
    fresh = [
        f"--config_path={preset}",
        f"--dataset.repo_id=local/levers_{task}_{root.name}",
        f"--dataset.episodes=[{','.join(str(e) for e in train_episodes(root))}]",
        f"--job_name=levers_{task}_{root.name}",
        f"--policy.n_members={members}",
    ]
    common = [
        f"--dataset.root={root}",
        f"--dataset.video_backend={resolve_video_backend()}",
        f"--save_freq={reference['save_freq']}",
    ]
    timing = out.parent / f"{out.name}.train_s.json"  # beside the run: lerobot-train owns its output_dir
    done: list[Path] = []
    spent = _timed(
        timing, "train_s", lambda: done.append(run_lerobot_train(out, fresh, int(reference["steps"]), common))
    )
    return done[0], spent


def chained(pretrained: Path, chain_dir: Path, scripted_regrasp: bool = False) -> Path:
    """A ``suture_chain`` around a checkpoint (``lerobot-suture chain --policy``): the high level inside the policy
    reads each step's subtask from the measured pose and the marks, as on a robot; with ``scripted_regrasp`` its
    servo takes the needle's tip and the checkpoint pulls."""
    from lerobot_policy_suture_chain.assemble import ChainCommandConfig, write_chain

    if not (chain_dir / "config.json").is_file():
        write_chain(
            ChainCommandConfig(output_dir=chain_dir, policy=pretrained, scripted_regrasp=scripted_regrasp)
        )
    return chain_dir


def evaluate(
    task: str,
    pretrained: Path,
    episodes: int,
    seed: int,
    batch_envs: int,
    condition: str = "nominal",
    env_overrides: dict | None = None,
) -> dict:
    """The checkpoint on the board's test seeds of ``task`` in one ``condition`` (a scenario): the leaderboard's
    cell. A checkpoint trained on relative actions composes them with the measured pose in its own
    post-processor, so every line runs on the same env. ``env_overrides``: env arguments on top of those the
    checkpoint's inputs name (``regrasp_from``)."""
    from lerobot_suture.leaderboard import cells
    from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy
    from lerobot_suture.sim.tasks import task_spec

    runner = PolicyRunner.from_pretrained(pretrained, GateMode.REPORT, "cpu", {})
    seeds = cells.condition_seeds(seed, task, condition, episodes)
    env_kwargs = env_kwargs_for_policy(runner.policy.config) | (env_overrides or {})
    logs, seconds = cells.cell_episodes(runner, env_kwargs, task, condition, seeds, batch_envs)
    return cells.summarize_cell(logs, seconds, throws=task_spec(task).throws)


def _reported(cell: dict) -> dict:
    """The part of a cell a line reports (``per_throw`` where the task has throws)."""
    keys = (
        "episodes",
        "successes",
        "success_rate",
        "success_interval",
        "mean_steps",
        "seconds",
        "per_episode",
        "per_throw",
    )
    return {k: cell[k] for k in keys if k in cell}


def _with_earlier_lines(lines: list[dict], output: Path | None, task: str, members: int) -> list[dict]:
    """``lines`` with the lines of the other levers that ``output`` already holds for the same task and
    members (a run of some levers adds to the table), in the order of :data:`LEVERS`."""
    if output is None or not output.is_file():
        return lines
    earlier = json.loads(output.read_text())
    if (earlier.get("task"), earlier.get("members")) != (task, members):
        return lines
    by_name = {line["lever"]: line for line in earlier["levers"]} | {line["lever"]: line for line in lines}
    return [by_name[lever.name] for lever in LEVERS if lever.name in by_name]


def figure(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lerobot_suture.plotting import save_figure

    lines = report["levers"]
    fig, ax = plt.subplots(figsize=(8, 1.2 + 0.6 * len(lines)))
    throws = all(
        "per_throw" in line["nominal"] for line in lines
    )  # a long task: its first throw on the marks
    for i, line in enumerate(lines):
        cell = line["nominal"]
        rate, (low, high) = cell["success_rate"], cell["success_interval"]
        if throws:
            first = cell["per_throw"]["throws"][0]["on_marks"]
            rate, (low, high) = first["rate"], first["wilson_95"]
        ax.errorbar(
            rate,
            i,
            # Clipped: at a rate of 0 or 1 the interval's end can miss the rate by a rounding error.
            xerr=[[max(rate - low, 0.0)], [max(high - rate, 0.0)]],
            fmt="o",
            color="C0",
            capsize=3,
        )
    labels = [textwrap.fill(f"{line['lever']} ({line['episodes']} ep.)", 40) for line in lines]
    ax.set_yticks(range(len(lines)), labels, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlim(0, 1)
    what = "first throws on the marks" if throws else "success"
    ax.set_xlabel(f"nominal {what}, {lines[0]['nominal']['episodes']} test seeds, 95% Wilson")
    fig.suptitle(f"{report['task']}: what each lever does ({report['members']} member(s))", fontsize=10)
    ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def _slug(name: str) -> str:
    """A lever's folder name."""
    return name.replace(" + ", "_").replace(", ", "_").replace(" ", "_")


def main() -> None:
    from lerobot_suture.sim.tasks import TASK_NAMES, task_spec

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", required=True, choices=TASK_NAMES)
    parser.add_argument("--members", type=int, default=1, help="ensemble members (1: the member recipe)")
    parser.add_argument("--levers", nargs="*", default=[lever.name for lever in LEVERS])
    parser.add_argument("--episodes", type=int, default=50, help="test episodes a line")
    parser.add_argument("--seed", type=int, default=7_000_000, help="the leaderboard's base of test seeds")
    parser.add_argument("--batch-envs", type=int, default=8)
    parser.add_argument("--work-dir", type=Path, default=ROOT / "outputs" / "levers")
    parser.add_argument("--output", type=Path)
    parser.add_argument("--figure", type=Path)
    parser.add_argument(
        "--scenarios",
        action="store_true",
        help="each line also on the task's perturbation scenarios (the board's other cells), --episodes each",
    )
    args = parser.parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # a stage's time is kept when the run is stopped
    unknown = sorted(set(args.levers) - {lever.name for lever in LEVERS})
    if unknown:
        parser.error(f"unknown levers {unknown}; choose among {[lever.name for lever in LEVERS]}")

    work = args.work_dir / args.task
    work.mkdir(parents=True, exist_ok=True)
    lines = []
    by_name = {lever.name: lever for lever in LEVERS}
    for lever in (by_name[name] for name in dict.fromkeys(args.levers)):  # in the order asked
        slug = _slug(lever.name)
        trained = by_name[lever.checkpoint_of] if lever.checkpoint_of else lever
        root, log = work / "data" / _slug(trained.name), work / f"{_slug(trained.name)}.log"
        print(f"[{lever.name}] recording ...", flush=True)
        recorded = record(args.task, trained, root, log)
        print(f"[{lever.name}] training {args.members} member(s) ...", flush=True)
        out = work / "train" / f"{_slug(trained.name)}_n{args.members}"
        pretrained, train_s = train(args.task, root, out, args.members)
        if lever.subtask or lever.scripted_regrasp:  # the chain's high level, as lerobot-eval runs it
            pretrained = chained(
                pretrained, work / "chains" / f"{slug}_n{args.members}", lever.scripted_regrasp
            )
        conditions = task_spec(args.task).scenarios if args.scenarios else ("nominal",)
        by_condition = {}
        for condition in conditions:
            name = f"{slug}_n{args.members}" + ("" if condition == "nominal" else f".{condition}")
            cell_path = work / "cells" / f"{name}.json"
            if cell_path.is_file():
                by_condition[condition] = json.loads(cell_path.read_text())
                continue
            print(f"[{lever.name}] evaluating {args.episodes} test episodes, {condition} ...", flush=True)
            overrides = {} if lever.regrasp_from == "marks" else {"regrasp_from": lever.regrasp_from}
            cell = evaluate(
                args.task, pretrained, args.episodes, args.seed, args.batch_envs, condition, overrides
            )
            cell_path.parent.mkdir(parents=True, exist_ok=True)
            cell_path.write_text(json.dumps(cell))
            by_condition[condition] = cell
        lines.append(
            {
                "lever": lever.name,
                "episodes": recorded["episodes"],
                "wrist_camera": lever.wrist_camera,
                "marks": lever.marks,
                "subtask": lever.subtask,
                "relative_actions": lever.relative_actions,
                "regrasp_miss": lever.regrasp_miss,
                "regrasp_noise": lever.regrasp_noise,
                "regrasp_target": lever.regrasp_target,
                "regrasp_from": lever.regrasp_from,
                "regrasp_settle": lever.regrasp_settle,
                "regrasp_reach_offset": lever.regrasp_reach_offset,
                "scripted_regrasp": lever.scripted_regrasp,
                **({"checkpoint_of": lever.checkpoint_of} if lever.checkpoint_of else {}),
                "record_s": recorded["record_s"],
                "train_s": round(train_s, 1),
                "nominal": _reported(by_condition["nominal"]),
                **(
                    {"scenarios": {c: _reported(cell) for c, cell in by_condition.items() if c != "nominal"}}
                    if len(by_condition) > 1
                    else {}
                ),
            }
        )
        for condition, cell in by_condition.items():
            print(f"[{lever.name}] {condition}: {cell['successes']}/{cell['episodes']} successes", flush=True)
    lines = _with_earlier_lines(lines, args.output, args.task, args.members)
    report = {"task": args.task, "members": args.members, "machine": machine(), "levers": lines}
    if args.figure is not None:
        figure(report, args.figure)
    emit(report, args.output)


if __name__ == "__main__":
    main()
