"""What the inference approximations cost the ensemble: fewer samples per member (K) and fewer DDIM
denoising steps, against the trained configuration, in closed loop.

Each configuration loads the same checkpoint with config overrides (as `lerobot-eval --policy.path=DIR
--policy.uncertainty_samples_per_member=K --policy.num_inference_steps=S` does) and runs the insertion
task's conditions (nominal and the paper's four scenarios) on the leaderboard's test seeds, the CBF on and
the gate scoring every prediction. Reported per configuration: episodes per minute, success per condition
(Wilson 95%), the gate's episode-level AUROC per scenario against the nominal episodes (DeLong 95%;
threshold-free), and how many episodes end as they do under the first configuration, the reference.

A gate's calibration is bound to the K and S it was fitted with (the policy refuses to load it under
others: its threshold would not hold), so every configuration runs from a copy of the checkpoint without
its calibration, and no alarm rate is reported: a deployment that keeps an approximation calibrates it
anew. Prints JSON; `--plot FILE` draws success and AUROC against the denoising work per prediction.

    python studies/benchmarks/eval_approximations.py --policy-path outputs/.../pretrained_model
        [--configs 8x10 4x10 1x10 8x5 4x5] [--episodes 50] [--workers 2] [--output FILE] [--plot FILE]

A configuration is KxS: K chunks per member, S DDIM steps. Time it with nothing else running.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))  # the product's _report
from _report import emit, machine  # noqa: E402

from lerobot_suture.experiments import metrics  # noqa: E402
from lerobot_suture.experiments.episode_metrics import ood_metrics  # noqa: E402
from lerobot_suture.leaderboard import cells as leaderboard  # noqa: E402
from lerobot_suture.leaderboard.pipeline import LeaderboardConfig  # noqa: E402
from lerobot_suture.pipelines.stages import code_commit  # noqa: E402
from lerobot_suture.plotting import save_figure  # noqa: E402
from lerobot_suture.runtime.policy import GateMode, PolicyRunner, copy_with_overrides, env_kwargs_for_policy  # noqa: E402
from lerobot_suture.sim.tasks import task_spec  # noqa: E402

NEEDS = "a trained, calibrated ensemble (--policy-path)"
TASK = "insertion"
LEADERBOARD_SEED = LeaderboardConfig.seed  # the leaderboard's test seeds: the reference's cells are its own


def parse_config(text: str) -> dict:
    samples, _, steps = text.partition("x")
    if not (samples.isdigit() and steps.isdigit()):
        raise SystemExit(f"A configuration is KxS (samples per member x DDIM steps), e.g. 4x5. Got {text!r}.")
    return {"uncertainty_samples_per_member": int(samples), "num_inference_steps": int(steps)}


def run_config(
    policy_path: Path, overrides: dict, episodes: int, batch_envs: int, workers: int, seed: int
) -> tuple[dict, dict]:
    """One configuration's figures, and its per-episode outcomes by condition (for the agreement check)."""
    runner = PolicyRunner.from_pretrained(policy_path, GateMode.REPORT, overrides=overrides)
    env_kwargs = env_kwargs_for_policy(runner.policy.config)
    logs, seconds = {}, 0.0
    for condition in task_spec(TASK).scenarios:  # each run as the leaderboard runs its cell
        seeds = leaderboard.condition_seeds(seed, TASK, condition, episodes)
        logs[condition], elapsed = leaderboard.cell_episodes(
            runner, env_kwargs, TASK, condition, seeds, batch_envs, workers
        )
        seconds += elapsed
    nominal = logs["nominal"]
    per_condition = {}
    for condition, runs in logs.items():
        successes = sum(log.success for log in runs)
        cell = {
            "success_rate": successes / len(runs),
            "success_interval": metrics.wilson_interval(successes, len(runs)),
        }
        if condition != "nominal":
            ood = ood_metrics(nominal, runs)
            cell |= {k: ood[k] for k in ("auroc", "auroc_interval95")}
        per_condition[condition] = cell
    total = sum(len(runs) for runs in logs.values())
    row = {
        "samples_per_member": overrides["uncertainty_samples_per_member"],
        "ddim_steps": overrides["num_inference_steps"],
        "unet_evaluations_per_prediction": runner.policy.config.n_members
        * overrides["uncertainty_samples_per_member"]
        * overrides["num_inference_steps"],
        "episodes": total,
        "seconds": round(seconds, 1),
        "episodes_per_min": round(60.0 * total / seconds, 1),
        "conditions": per_condition,
    }
    outcomes = {c: [(log.seed, bool(log.success)) for log in runs] for c, runs in logs.items()}
    return row, outcomes


def agreement(reference: dict, other: dict) -> float:
    """The share of episodes (same seeds) whose success is the reference configuration's."""
    pairs = [(a, b) for c in reference for a, b in zip(reference[c], other[c], strict=True)]
    assert all(a[0] == b[0] for a, b in pairs)
    return float(np.mean([a[1] == b[1] for a, b in pairs]))


def plot(rows: list[dict], path: Path) -> None:
    """Success and AUROC per condition against the measured episodes per minute, a point per configuration."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    conditions = list(rows[0]["conditions"])
    speed = [row["episodes_per_min"] for row in rows]
    fig, (ax_success, ax_auroc) = plt.subplots(1, 2, figsize=(11, 4.6))
    for condition in conditions:
        ax_success.plot(
            speed, [r["conditions"][condition]["success_rate"] for r in rows], "o", label=condition
        )
        if condition != "nominal":
            ax_auroc.plot(speed, [r["conditions"][condition]["auroc"] for r in rows], "o", label=condition)
    for ax, title in ((ax_success, "policy success"), (ax_auroc, "gate AUROC against nominal")):
        ax.set_xlabel("episodes per minute (2 cores)")
        ax.set_title(title, pad=22)
        ax.set_ylim(-0.03, 1.03)
        ax.grid(alpha=0.3)
        for row in rows:
            label = f"K={row['samples_per_member']}\nS={row['ddim_steps']}"
            ax.annotate(label, (row["episodes_per_min"], 1.03), fontsize=7, ha="center", va="bottom")
        ax.legend(fontsize=7, loc="center", bbox_to_anchor=(0.5, 0.3))
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--policy-path", type=Path, required=True)
    parser.add_argument("--configs", nargs="+", default=["8x10", "4x10", "1x10", "8x5", "4x5"])
    parser.add_argument("--episodes", type=int, default=50, help="per condition")
    parser.add_argument("--batch-envs", type=int, default=8)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=LEADERBOARD_SEED)
    parser.add_argument("--output", type=Path, default=None)
    parser.add_argument("--plot", type=Path, default=None)
    args = parser.parse_args()

    configs = [parse_config(c) for c in args.configs]
    rows, reference = [], None
    scratch = tempfile.TemporaryDirectory(prefix="eval_approximations_")
    # the checkpoint without its calibration (copy_with_overrides leaves it out)
    policy_copy = copy_with_overrides(args.policy_path, Path(scratch.name) / "pretrained_model", {})
    for overrides in configs:
        row, outcomes = run_config(
            policy_copy, overrides, args.episodes, args.batch_envs, args.workers, args.seed
        )
        if reference is None:
            reference = outcomes
        row["same_success_as_reference"] = agreement(reference, outcomes)
        rows.append(row)
    for row in rows:
        row["speed_up_vs_reference"] = round(row["episodes_per_min"] / rows[0]["episodes_per_min"], 2)
    if args.plot is not None:
        plot(rows, args.plot)
    emit(
        {
            "benchmark": "eval_approximations",
            "code_commit": code_commit(),
            "policy_path": str(args.policy_path),
            "task": TASK,
            "seed": args.seed,
            "episodes_per_condition": args.episodes,
            "batch_envs": args.batch_envs,
            "workers": args.workers,
            "torch_threads_one_process": torch.get_num_threads(),
            "machine": machine(),
            "configurations": rows,
        },
        args.output,
    )


if __name__ == "__main__":
    main()
