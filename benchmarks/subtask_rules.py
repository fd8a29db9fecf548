"""The running suture's high level (``lerobot_suture.sim.subtasks``) against the scripted expert's own stages.

The expert finishes running sutures on ``--episodes`` seeds, nominal and in each of ``--scenarios``; at every control
step the rules read only the measured pose (jaw position and closure) and name the subtask and the throw, and the
expert's plan names the stage it is executing. Prints JSON, per scenario: the share of steps on which they agree,
overall and per stage, the confusion counts, each boundary's lag (the rules' switch minus the expert's, in control
steps), and whether the rules end on the throw the env counts.

    .venv/bin/python benchmarks/subtask_rules.py [--episodes 20] [--scenarios needle_drop ...] [--output FILE]
"""

from __future__ import annotations

import argparse
import collections
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
from _report import emit, machine  # noqa: E402
from tqdm import tqdm  # noqa: E402

from lerobot_suture.expert import ScriptedExpert  # noqa: E402
from lerobot_suture.registration import make_suture_env  # noqa: E402
from lerobot_suture.runtime.seeds import fresh_seeds  # noqa: E402
from lerobot_suture.sim.subtasks import SUBTASKS, SubtaskRules  # noqa: E402
from lerobot_suture.sim.wound_marks import MARKS_KEY  # noqa: E402

SEED_OFFSET = 700_000


def labelled_suture(env, seed: int, marks: bool) -> tuple[list[str], list[tuple[str, int]], dict]:
    """The expert's stage and the rules' (subtask, throw) at every control step of one suture (``marks``: the rules
    read the wound's marks too), and its last info."""
    expert, rules = ScriptedExpert(), SubtaskRules()
    observation, info = env.reset(seed=seed)
    expert.reset(env)
    ours = [rules.reset(observation["agent_pos"])]
    theirs = []
    while True:
        action = expert.act(env)
        theirs.append(expert.stage)  # the expert's own stage: the benchmark's ground truth
        observation, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            return theirs, ours, info
        ours.append(rules.update(observation["agent_pos"], observation.get(MARKS_KEY) if marks else None))


def switches(labels: list[str]) -> list[tuple[int, str, str]]:
    """(step, from, to) of every change of label."""
    return [(k, a, b) for k, (a, b) in enumerate(zip(labels, labels[1:], strict=False), start=1) if a != b]


def measure(scenario: str, seeds: list[int], marks: bool) -> dict:
    """The rules against the expert on ``seeds`` of ``scenario``."""
    env = make_suture_env(
        task="running_suture", obs_type="pixels_agent_pos", image_size=32, scenario=scenario, marks=True
    )
    confusion: collections.Counter = collections.Counter()
    lags: dict[str, list[int]] = collections.defaultdict(list)
    throws_match = successes = 0
    for seed in tqdm(seeds, desc=scenario, unit="suture", file=sys.stderr):
        theirs, ours, info = labelled_suture(env, seed, marks)
        subtasks = [subtask for subtask, _ in ours]
        confusion.update(zip(theirs, subtasks, strict=True))
        rule_switches = switches(subtasks)
        for step, before, after in switches(theirs):
            matching = [s for s, b, a in rule_switches if (b, a) == (before, after)]
            if matching:
                lags[f"{before}->{after}"].append(min(matching, key=lambda s: abs(s - step)) - step)
        throws_match += ours[-1][1] == info.get("throw_index")
        successes += bool(info["is_success"])
    env.close()
    total = sum(confusion.values())
    per_stage = {
        stage: round(confusion[(stage, stage)] / n, 4)
        for stage in SUBTASKS
        if (n := sum(v for (a, _), v in confusion.items() if a == stage))
    }
    return {
        "episodes": len(seeds),
        "expert_successes": successes,
        "steps": total,
        "agreement": round(sum(confusion[(s, s)] for s in SUBTASKS) / total, 4),
        "agreement_per_stage": per_stage,
        "confusion": {f"{a}->{b}": n for (a, b), n in sorted(confusion.items())},
        "boundary_lag_steps": {
            k: {"n": len(v), "median": float(np.median(v)), "min": int(min(v)), "max": int(max(v))}
            for k, v in sorted(lags.items())
        },
        "last_throw_matches_env": throws_match,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--scenarios", nargs="*", default=[])
    parser.add_argument("--no-marks", action="store_true", help="the rules read the measured pose alone")
    parser.add_argument("--output", type=Path, default=None)
    args = parser.parse_args()
    start = time.perf_counter()
    seeds = fresh_seeds(args.episodes, start=SEED_OFFSET)
    marks = not args.no_marks
    report = {"benchmark": "subtask_rules", "marks": marks, "seeds": [seeds[0], seeds[-1]]}
    report.update(measure("nominal", seeds, marks))
    report["scenarios"] = {scenario: measure(scenario, seeds, marks) for scenario in args.scenarios}
    report["machine"] = machine()
    report["wall_s"] = round(time.perf_counter() - start, 1)
    emit(report, args.output)


if __name__ == "__main__":
    main()
