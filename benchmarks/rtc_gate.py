"""The ensemble's gate under LeRobot's real-time chunking engine, calibrated at that engine's cadence, against the
sync engine's gate on the same seeds: where each hands over, nominal and in the paper's scenarios.

Under real-time chunking the policy predicts back to back, each chunk inpainted after the actions still
committed, and the gate scores the steps after them: another score distribution than the one calibrated on the
env path, at the sync engine's cadence. Three stages, each on the real-time clock at 10 Hz with
``lerobot-rollout --strategy.type=gated_dagger`` (the gate, the CBF, the scripted surgeon after a handover):

1. ``calibrate``: ``--calibration-episodes`` nominal scenes of the env path's calibration seeds (fresh seeds from
   1,000,000) under real-time chunking, with ``--policy.ood.calibration_file`` naming the file about to be
   written, so the gate reports and never hands over; then ``lerobot-suture calibrate --rollouts`` fits the
   gate on them into that file, in the policy directory (``--rtc-calibration``, ``ood_calibration_rtc.json``;
   an existing file is used as it is: the policy's own, ``ood_calibration.json``, runs the sync engine's gate under
   real-time chunking).
2. ``compare``: nominal (``--episodes``) and each of the paper's scenarios (``--scenario-episodes``), on the test
   seeds from ``--seed``, both engines: sync with the policy's own calibration, real-time chunking with the new
   one. Per seed, success and the frame at which the gate handed over.
3. The handovers against the bar: at the sync engine's frame or at most one chunk (``n_action_steps``) later.

Prints one JSON object (and writes it to ``--out`` after every stage; a stage whose outputs are in
``--work-dir`` is not run again)::

    .venv/bin/python benchmarks/rtc_gate.py --policy-path outputs/reproduce/train/checkpoints/last/pretrained_model
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
from _report import emit, write
from lerobot_policy_ensemble_diffusion.configuration_ensemble_diffusion import RTC_SCORES
from robot_path import SCENARIOS, _run, compare_engines, gated_outcomes, gated_rollout

from lerobot_suture.runtime.policy import copy_with_overrides
from lerobot_suture.runtime.seeds import FRESH_SEED_BASE
from lerobot_suture.safety.ood.calibration_file import calibration_report_file

NEEDS = "a trained, calibrated ensemble_diffusion policy (--policy-path)"
RTC_CALIBRATION_FILE = "ood_calibration_rtc.json"


def handover_bar(sync: dict[int, dict], rtc: dict[int, dict], chunk: int) -> dict:
    """Per seed of both runs: does real-time chunking hand over where sync does, or at most ``chunk`` frames
    later (and not where sync does not)?"""
    kinds = {"neither": 0, "within": 0, "earlier": 0, "later": 0, "only_sync": 0, "only_rtc": 0}
    for seed in sorted(set(sync) & set(rtc)):
        a, b = sync[seed]["handover"], rtc[seed]["handover"]
        if a is None or b is None:
            kinds["neither" if a is None and b is None else "only_sync" if b is None else "only_rtc"] += 1
        else:
            kinds["earlier" if b < a else "within" if b - a <= chunk else "later"] += 1
    met = kinds["neither"] + kinds["within"]
    return {**kinds, "seeds_meeting_bar": met, "seeds": sum(kinds.values())}


def with_rtc_score(policy_path: Path, rtc_score: str, copy: Path) -> Path:
    """A copy of the policy at ``copy`` whose gate reads ``rtc_score`` under real-time chunking, with the
    policy's own calibration: the sync engine's scores do not depend on it. Made once; a rerun reuses it."""
    if not (copy / "config.json").is_file():
        own = json.loads((policy_path / "config.json").read_text())["ood"]["calibration_file"]
        shutil.rmtree(copy, ignore_errors=True)
        copy_with_overrides(policy_path, copy, {"rtc_score": rtc_score})
        for name in (own, calibration_report_file(own)):
            shutil.copy2(policy_path / name, copy / name)
    return copy


def plot_handovers(compared: dict, chunk: int, rtc_calibration: str, rtc_score: str, path: Path) -> None:
    """Per scenario, each seed's handover frame under real-time chunking against sync's (a seed without one at
    -1), with the band the bar allows, to ``path`` (PNG)."""
    from matplotlib.figure import Figure

    from lerobot_suture.plotting import save_figure

    figure = Figure(figsize=(3.0 * len(compared), 3.2), dpi=120)
    for index, (scenario, found) in enumerate(compared.items()):
        axes = figure.add_subplot(1, len(compared), index + 1)
        frames = found["handover_frames"]
        pairs = [
            (frames["sync"][seed], frames["rtc"][seed]) for seed in frames["sync"] if seed in frames["rtc"]
        ]
        pairs = np.array([[-1 if a is None else a, -1 if b is None else b] for a, b in pairs], dtype=float)
        top = max(10.0, float(pairs.max()) + 2) if pairs.size else 10.0
        line = np.array([-1.0, top])  # (-1, -1): neither hands over, which meets the bar
        axes.fill_between(line, line, line + chunk, color="tab:green", alpha=0.2, linewidth=0)
        axes.plot(line, line, color="k", linewidth=0.6)
        if pairs.size:
            jitter = np.random.default_rng(0).uniform(-0.15, 0.15, pairs.shape)
            axes.scatter(*(pairs + jitter).T, s=14, color="tab:blue")
        bar = found["handover_bar"]
        axes.set_title(f"{scenario}: {bar['seeds_meeting_bar']} of {bar['seeds']}", fontsize=9)
        axes.set_xlim(-2, top)
        axes.set_ylim(-2, top)
        axes.set_xlabel("sync handover frame (-1: none)", fontsize=8)
        if index == 0:
            axes.set_ylabel("real-time chunking handover frame", fontsize=8)
    figure.suptitle(
        f"Handovers; sync's gate reads the policy's calibration, real-time chunking's {rtc_calibration} "
        f"(rtc_score {rtc_score}); green: the bar (up to {chunk} frames later)",
        fontsize=9,
    )
    figure.tight_layout()
    save_figure(figure, path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy-path", type=Path, required=True)
    parser.add_argument(
        "--calibration-episodes", type=int, default=50, help="nominal scenes the RTC gate is fit on"
    )
    parser.add_argument("--episodes", type=int, default=50, help="nominal test scenes per engine")
    parser.add_argument("--scenario-episodes", type=int, default=10, help="per scenario and engine")
    parser.add_argument("--seed", type=int, default=2_000_000, help="first test seed (the experiments')")
    parser.add_argument("--episode-s", type=float, default=14.0, help="wall time of an episode at most")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--figure", type=Path, help="a PNG of the handover frames, per scenario")
    parser.add_argument(
        "--rtc-calibration",
        default=RTC_CALIBRATION_FILE,
        help="the file in the policy directory the real-time engine's gate reads; fitted (stage 1) when absent. "
        "The policy's own (ood_calibration.json): the sync engine's gate under real-time chunking",
    )
    parser.add_argument(
        "--rtc-score",
        choices=RTC_SCORES,
        help="the policy's `rtc_score` for both engines (what the gate reads under real-time chunking): another "
        "than the policy's runs a copy of it in --work-dir, with the policy's own sync calibration",
    )
    parser.add_argument("--work-dir", type=Path, required=True, help="the commands' outputs; rerun to resume")
    args = parser.parse_args()
    config = json.loads((args.policy_path / "config.json").read_text())
    if config.get("type") != "ensemble_diffusion":
        raise SystemExit(f"--policy-path must be an ensemble_diffusion policy; {args.policy_path} is not.")
    if args.rtc_score is not None and args.rtc_score != config.get("rtc_score", "inpainted"):
        args.policy_path = with_rtc_score(args.policy_path, args.rtc_score, args.work_dir / "policy")
        config = json.loads((args.policy_path / "config.json").read_text())
    chunk = int(config["n_action_steps"])
    result: dict = {
        "command": " ".join(["python", *sys.argv]),
        "policy_path": str(args.policy_path),
        "rtc_calibration_file": args.rtc_calibration,
        "rtc_score": config.get("rtc_score", "inpainted"),
        "calibration_first_seed": FRESH_SEED_BASE,
        "first_seed": args.seed,
        "queue_threshold": "LeRobot's default, 30",
        "chunk_frames": chunk,
    }

    def save() -> None:
        if args.out is not None:
            write(result, args.out)

    calibration = args.policy_path / args.rtc_calibration
    report_file = args.policy_path / calibration_report_file(args.rtc_calibration)
    if not calibration.is_file():
        start = time.perf_counter()
        shutil.rmtree(args.work_dir / "calibration", ignore_errors=True)  # an interrupted run's scratch
        _, root = gated_rollout(
            args.policy_path,
            "rtc",
            args.work_dir / "calibration",
            seed=FRESH_SEED_BASE,
            episodes=args.calibration_episodes,
            episode_s=args.episode_s,
            duration=0,
            calibration_file=args.rtc_calibration,
        )
        _run(
            "lerobot-suture",
            [
                "calibrate",
                f"--policy.path={args.policy_path}",
                f"--rollouts={root}",
                f"--calibration_file={args.rtc_calibration}",
            ],
            args.work_dir / "calibrate.log",
        )
        result["calibration_seconds"] = round(time.perf_counter() - start, 1)
    fitted = json.loads(report_file.read_text())
    sync_threshold = json.loads((args.policy_path / config["ood"]["calibration_file"]).read_text())[
        "threshold"
    ]
    result["thresholds"] = {"sync": sync_threshold, "rtc": fitted["calibration"]["threshold"]}
    result["calibration_episodes"] = fitted.get("episodes", len(fitted.get("calibration_seeds", ())))
    save()

    runs = {**{name: args.scenario_episodes for name in SCENARIOS[1:]}, "nominal": args.episodes}
    result["compared"] = {}
    for scenario, episodes in runs.items():
        if episodes <= 0:
            continue
        run_dir, outcomes = args.work_dir / scenario, {}
        for engine, calibration_file in (("sync", None), ("rtc", args.rtc_calibration)):
            done = run_dir / f"{engine}_outcomes.json"
            if not done.is_file():
                shutil.rmtree(
                    run_dir / f"{engine}_dataset", ignore_errors=True
                )  # an interrupted run's scratch
                trace, root = gated_rollout(
                    args.policy_path,
                    engine,
                    run_dir,
                    seed=args.seed,
                    episodes=episodes,
                    episode_s=args.episode_s,
                    duration=0,
                    scenario=scenario,
                    calibration_file=calibration_file,
                )
                found = gated_outcomes(trace, root, f"local/rollout_robot_path_{engine}")
                done.write_text(json.dumps({str(seed): o for seed, o in found.items()}))
            outcomes[engine] = {int(seed): o for seed, o in json.loads(done.read_text()).items()}
        result["compared"][scenario] = {
            **compare_engines(outcomes["sync"], outcomes["rtc"]),
            "handover_bar": handover_bar(outcomes["sync"], outcomes["rtc"], chunk),
            "handover_frames": {
                engine: {str(seed): o["handover"] for seed, o in found.items()}
                for engine, found in outcomes.items()
            },
        }
        save()
    if args.figure is not None and result["compared"]:
        plot_handovers(result["compared"], chunk, args.rtc_calibration, result["rtc_score"], args.figure)
    result["work_dir"] = str(args.work_dir)
    emit(result, args.out)


if __name__ == "__main__":
    main()
