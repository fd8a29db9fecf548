"""Why a chained extract misses a throw left on the marks: how far the needle lies from the planned regrasp.

The planned regrasp (``sim.extraction.planned_regrasp``) assumes the needle of a throw on its marks lies on the
arc planned through them; the extraction task starts every episode with the expert's own throw, on that arc.
In the running suture a learned insert leaves the needle wherever its throw ended, on the marks within the 2 mm
tolerance but not on the plan. For the given seeds of the running suture's nominal cell (the board's seeds, the CBF
on), a ``suture_chain`` runs, and at every step of the first throw's extract (the env's own phase, privileged) this
reads the simulator: the distance from the planned grasp's jaw point to the needle's wire (across it, the one a
closing cannot absorb), the closest the jaw came to the plan and to the wire, and how often the jaw closed; how
long the insert held on after the throw was over (``steps_to_release``) and how far it strained the tissue
meanwhile (``strain_before_release_mm``, against the extraction's 2 mm bound), and the strain the bound counts at
the extract's last step (``extraction_strain_mm``: when the throw is extracted, or the episode ends); which rule
of the capture let the needle go at each closing (``grasp.CaptureVerdict``: not between the faces, the jaw too
closed, lodged, into the pad; with how far the seat would move the needle, mm), whether a closing caught it and how far the jaw then
travelled (``pulled_mm``). The same for the regrasp planned from the release
(``sim.regrasp_target.released_regrasp`` of the jaw's pose at the extract's first step, the needle still held):
``release_plan_to_wire_mm``, ``closest_jaw_to_release_plan_mm``. ``--regrasp-from release`` gives a chain that
reads the plan that one.
Prints one JSON object.

    .venv/bin/python studies/benchmarks/chain_extract_offsets.py --policy-path CHAIN_DIR --seeds 37000004 ...
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402
from _lockstep import emit, machine, roll_out_lockstep  # noqa: E402

import lerobot_suture  # noqa: E402,F401
from lerobot_suture.runtime.policy import env_kwargs_for_policy, reporting_runner  # noqa: E402
from lerobot_suture.sim.extraction import planned_regrasp  # noqa: E402
from lerobot_suture.sim.geometry import NEEDLE_ARC, NEEDLE_RADIUS  # noqa: E402
from lerobot_suture.sim.regrasp_target import released_regrasp  # noqa: E402

NEEDS = "a trained running-suture chain (--policy-path) and the seeds to study (--seeds)"


def wire_distance(point: np.ndarray, needle_position: np.ndarray, needle_rotation: np.ndarray) -> float:
    """Distance (m) from ``point`` to the needle's wire: the arc of radius ``NEEDLE_RADIUS`` in its xy-plane,
    from the tip (angle 0) to the tail (``NEEDLE_ARC``)."""
    local = needle_rotation.T @ (point - needle_position)
    angle = float(np.arctan2(local[1], local[0]) % (2.0 * np.pi))
    # Off the arc, the nearer end: the tip past the middle of the gap, else the tail.
    angle = 0.0 if angle > 0.5 * (NEEDLE_ARC + 2.0 * np.pi) else min(angle, NEEDLE_ARC)
    nearest = NEEDLE_RADIUS * np.array([np.cos(angle), np.sin(angle), 0.0])
    return float(np.linalg.norm(local - nearest))


def _reported(value):
    if isinstance(value, float):
        return round(value, 3) if np.isfinite(value) else None
    return value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy-path", type=Path, required=True)
    parser.add_argument("--seeds", type=int, nargs="+", required=True)
    parser.add_argument("--output", type=Path)
    parser.add_argument("--regrasp-from", choices=("marks", "release"), default="marks")
    parser.add_argument("--arc-guard", action="store_true", help="hold the needle in tissue to its arc")
    args = parser.parse_args()
    runner = reporting_runner(args.policy_path)
    env_kwargs = env_kwargs_for_policy(runner.policy.config)
    if args.regrasp_from != "marks":
        env_kwargs["regrasp_from"] = args.regrasp_from
    if args.arc_guard:
        env_kwargs["arc_guard"] = True
    out = [
        {
            "seed": s,
            "extract_steps": 0,
            "plan_to_wire_mm": None,
            "release_plan_to_wire_mm": None,
            "closest_jaw_to_plan_mm": np.inf,
            "closest_jaw_to_release_plan_mm": np.inf,
            "closest_jaw_to_wire_mm": np.inf,
            "closings": 0,
            "closing_verdicts": [],
            "caught": False,
            "pulled_mm": None,
            "steps_to_release": None,
            "strain_before_release_mm": None,
            "extraction_strain_mm": None,
            "_closure": None,
            "_verdict": None,
            "_strain_over": None,
            "_caught_at": None,
        }
        for s in args.seeds
    ]
    release_plans: dict[int, np.ndarray] = {}

    def on_step(i: int, u, info: dict) -> None:
        ep = out[i]
        if u.throw_index != 0 or u.throw_phase != "extract":
            return
        strain = 1e3 * float(info["tissue_strain"])
        if ep["_strain_over"] is None:  # the throw is over; the insert has yet to let go
            ep["_strain_over"] = strain
        ep["extraction_strain_mm"] = strain - ep["_strain_over"]  # the bound's count, insert's last steps in
        if ep["steps_to_release"] is None and u.needle_grasped:
            ep["strain_before_release_mm"] = strain - ep["_strain_over"]
        elif ep["steps_to_release"] is None:
            ep["steps_to_release"] = ep["extract_steps"]
        needle_position, needle_rotation = u.needle_pose()
        plan_position, _ = planned_regrasp(u.entry_point, u.exit_point, u.phantom_rotation[:, 2])
        jaw_position, _ = u.jaw_pose()
        if ep["plan_to_wire_mm"] is None:  # the needle as the insert left it, still held
            ep["plan_to_wire_mm"] = 1e3 * wire_distance(plan_position, needle_position, needle_rotation)
            release_plans[i], _ = released_regrasp(*u.jaw_pose())
            ep["release_plan_to_wire_mm"] = 1e3 * wire_distance(
                release_plans[i], needle_position, needle_rotation
            )
        ep["extract_steps"] += 1
        ep["closest_jaw_to_plan_mm"] = min(
            ep["closest_jaw_to_plan_mm"], 1e3 * np.linalg.norm(jaw_position - plan_position)
        )
        ep["closest_jaw_to_release_plan_mm"] = min(
            ep["closest_jaw_to_release_plan_mm"], 1e3 * np.linalg.norm(jaw_position - release_plans[i])
        )
        ep["closest_jaw_to_wire_mm"] = min(
            ep["closest_jaw_to_wire_mm"], 1e3 * wire_distance(jaw_position, needle_position, needle_rotation)
        )
        closure = u.jaw_closure_command
        if ep["_closure"] is not None and ep["_closure"] < 0.5 <= closure:
            ep["closings"] += 1
            if ep["_verdict"] is not None:  # judged on the state the step started from, as the env judged it
                shift = ep["_verdict"].shift
                ep["closing_verdicts"].append([ep["_verdict"].rule, None if np.isnan(shift) else 1e3 * shift])
        ep["_closure"] = closure
        held = bool(u.needle_grasped)
        if held and ep["_caught_at"] is None and ep["closings"]:
            ep["caught"], ep["_caught_at"] = True, jaw_position.copy()
        if ep["_caught_at"] is not None:
            ep["pulled_mm"] = 1e3 * float(np.linalg.norm(jaw_position - ep["_caught_at"]))
        ep["_verdict"] = None if held else u.capture_verdict()

    roll_out_lockstep(runner, env_kwargs, "running_suture", args.seeds, on_step)
    episodes = [
        {k: _reported(v) for k, v in ep.items() if not k.startswith("_")}  # inf: never in the extract
        for ep in out
    ]
    report = {
        "benchmark": "chain_extract_offsets",
        "policy": str(args.policy_path),
        "regrasp_from": args.regrasp_from,
        "arc_guard": args.arc_guard,
        "episodes": episodes,
        "machine": machine(),
    }
    emit(report, args.output)


if __name__ == "__main__":
    main()
