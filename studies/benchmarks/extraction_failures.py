"""Where a trained policy's extractions end: let go, regrasped near the tip, pulled out, out through the exit.

Rolls the policy out on the leaderboard's nominal ``extraction`` test seeds (``--seed`` is the leaderboard's
base, so the episodes are its ``nominal`` cell's: same seeds, the CBF on, each episode's noise from its
seed, the gate reporting) and reads the simulator's privileged state at every control step. An episode
starts with the needle through the tissue, held at its tail; an extraction succeeds when the jaw holds the
needle, all of it is out of the tissue, its tail left within 2 mm of the exit point and the tissue strain
stayed within 2 mm (``lerobot_suture.sim.extraction``). The scripted expert lets go, regrasps 0.25 rad of arc
from the tip and pulls along the arc. Prints one JSON object: how many episodes let go of the tail,
regrasped, pulled the needle out, and out through the exit hole within the strain bound; where the regrasps
sat (arc angle from the tip, degrees); and, for the episodes that let go and never caught the needle again,
the closest the jaw came to the expert's regrasp pose (mm and degrees); and where the strain accumulated:
before the first regrasp and during the pull, split into the needle centre's path (translation) and its
off-axis turn, beside the pull's drift (how far the centre ended from where the pull began), and the strain
when the needle came out (the bound is judged then; a needle turned on afterwards goes back in and strains
more). A pull whose path is many times its drift strains the tissue by jitter, not by a straight pull. And
every time the jaw closed before its first regrasp, which rule of the capture let the needle go
(``grasp.CaptureVerdict``: not between the faces, the jaw too closed, lodged: the seat would move the needle
in tissue by more than 0.5 mm, or into the pad) and by how much the seat would have moved the needle, with
where the jaw stood then and a chunk (4 control steps) before, off the expert's regrasp pose in that pose's
frame: along the wire (x), across the faces (y) and along the jaw (z); medians of each axis's size per rule.

    .venv/bin/python studies/benchmarks/extraction_failures.py --policy-path DIR [--episodes 50] [--output F.json]
"""

from __future__ import annotations

import math
import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402
from _lockstep import jaw_pose_error, roll_out_lockstep, run_nominal_seeds  # noqa: E402

import lerobot_suture  # noqa: E402,F401
from lerobot_suture.experiments.metrics import wilson_interval  # noqa: E402
from lerobot_suture.sim.extraction import REGRASP_ANGLE, STRAIN_BOUND, TAIL_EXIT_TOLERANCE  # noqa: E402
from lerobot_suture.sim.geometry import NEEDLE_RADIUS, grasp_transform, jaw_holding  # noqa: E402
from lerobot_suture.sim.tissue import off_arc_motion  # noqa: E402

NEEDS = "a trained extraction policy (--policy-path)"
TASK = "extraction"
CHUNK_STEPS = 4
"""How many control steps before a closing its earlier offset is read (the board's executed chunk)."""


def regrasp_error(u) -> tuple[float, float]:
    """How far the jaw is from the pose that holds the needle where the expert regrasps it (mm, deg)."""
    return jaw_pose_error(u, grasp_transform(REGRASP_ANGLE, 0.0, 0.0))


def regrasp_offset(u) -> list[float]:
    """Where the jaw is off the expert's regrasp pose, in that pose's frame (mm): x, y (across the faces), z."""
    target_pos, target_rot = jaw_holding(*u.needle_pose(), *grasp_transform(REGRASP_ANGLE, 0.0, 0.0))
    return [round(1e3 * float(v), 4) for v in target_rot.T @ (u.jaw_pose()[0] - target_pos)]


def roll_out(runner, env_kwargs: dict, seeds: list[int]) -> list[dict]:
    """``seeds`` in lockstep (one batch), the CBF on; per episode what the jaw did with the needle."""
    out = [
        {
            "seed": s,
            "let_go": False,
            "regrasp_angles_deg": [],
            "extracted": False,
            "closest_mm": math.inf,
            "closest_rotation_deg": None,
            "was_held": True,  # every episode starts with the needle held at its tail
            "strain_parts_mm": {"before_regrasp": [0.0, 0.0], "pull": [0.0, 0.0]},  # [path, turn]
            "pull_drift_mm": None,
            "strain_at_extraction_mm": None,
            "close_attempts": [],  # each closing before the first regrasp: [rule, shift mm, off the regrasp mm,
            # deg, offset (x, y, z mm) then, a chunk before]
            "_pose": None,
            "_pull_start": None,
            "_verdict": None,
            "_closure": 1.0,  # the episode starts holding the needle
            "_regrasp_error": None,
            "_offsets": [],  # regrasp_offset of the last CHUNK_STEPS + 1 steps
        }
        for s in seeds
    ]

    def on_step(i: int, u, info: dict) -> None:
        ep = out[i]
        held = bool(u.needle_grasped)
        closure = u.jaw_closure_command
        closing = ep["_closure"] < 0.5 <= closure
        if closing and ep["let_go"] and not ep["regrasp_angles_deg"] and ep["_verdict"] is not None:
            verdict = ep["_verdict"]  # judged on the state the step started from, as the env judged it
            shift = None if math.isnan(verdict.shift) else 1e3 * verdict.shift
            offsets = ep["_offsets"]
            ep["close_attempts"].append(
                [verdict.rule, shift, *ep["_regrasp_error"], offsets[-1], offsets[-1 - CHUNK_STEPS :][0]]
            )
        ep["_closure"] = closure
        if not held:
            ep["let_go"] = True
        if ep["let_go"] and not ep["regrasp_angles_deg"]:  # the reach before the first regrasp
            distance, rotation = regrasp_error(u)
            if distance < ep["closest_mm"]:
                ep["closest_mm"], ep["closest_rotation_deg"] = distance, rotation
        if held and not ep["was_held"]:  # a new grasp: where along the needle it sits
            ep["regrasp_angles_deg"].append(math.degrees(u.grasp_parameters[0]))
        ep["was_held"] = held
        centre, rotation = u.needle_pose()  # world; the nominal phantom does not move
        if ep["_pose"] is not None and (u.needle_in_tissue or not ep["extracted"]):
            path, turn = off_arc_motion(*ep["_pose"], centre, rotation, NEEDLE_RADIUS)
            part = ep["strain_parts_mm"]["pull" if ep["regrasp_angles_deg"] else "before_regrasp"]
            part[0] += 1e3 * path
            part[1] += 1e3 * turn
        if ep["regrasp_angles_deg"] and not ep["extracted"]:
            if ep["_pull_start"] is None:
                ep["_pull_start"] = centre.copy()
            ep["pull_drift_mm"] = 1e3 * float(np.linalg.norm(centre - ep["_pull_start"]))
        ep["_pose"] = (centre.copy(), rotation.copy())
        ep["_verdict"] = None if held else u.capture_verdict()
        ep["_regrasp_error"] = regrasp_error(u)
        ep["_offsets"] = [*ep["_offsets"][-CHUNK_STEPS:], regrasp_offset(u)]
        if not ep["extracted"] and not u.needle_in_tissue:  # out: what the bound is judged on
            ep["strain_at_extraction_mm"] = 1e3 * float(info["tissue_strain"])
        ep["extracted"] = ep["extracted"] or not u.needle_in_tissue
        tail = u.tail_exit_error
        ep["tail_exit_error_mm"] = None if math.isinf(tail) else 1e3 * tail
        ep["strain_mm"] = 1e3 * float(info["tissue_strain"])
        ep["success"] = bool(info["is_success"])
        ep["steps"] = int(u.step_index)

    roll_out_lockstep(runner, env_kwargs, TASK, seeds, on_step)
    for ep in out:
        for scratch in (
            "was_held",
            "_pose",
            "_pull_start",
            "_verdict",
            "_closure",
            "_regrasp_error",
            "_offsets",
        ):
            del ep[scratch]
        if math.isinf(ep["closest_mm"]):
            ep["closest_mm"] = None
    return out


def summarize(episodes: list[dict]) -> dict:
    """Counts with 95% Wilson intervals; where the regrasps sat; how near the misses came."""
    n = len(episodes)

    def count(flags: list[bool]) -> dict:
        k = sum(flags)
        return {"episodes": k, "rate": k / n, "interval": list(wilson_interval(k, n))}

    through_exit = [
        ep["tail_exit_error_mm"] is not None and ep["tail_exit_error_mm"] <= 1e3 * TAIL_EXIT_TOLERANCE
        for ep in episodes
    ]
    summary = {
        "let_go": count([ep["let_go"] for ep in episodes]),
        "regrasped": count([bool(ep["regrasp_angles_deg"]) for ep in episodes]),
        "extracted": count([ep["extracted"] for ep in episodes]),
        "tail_through_exit": count(through_exit),
        "strain_within_bound": count([ep["strain_mm"] <= 1e3 * STRAIN_BOUND for ep in episodes]),
        "success": count([ep["success"] for ep in episodes]),
        "median_strain_mm": float(np.median([ep["strain_mm"] for ep in episodes])),
        "bounds": {
            "strain_mm": 1e3 * STRAIN_BOUND,
            "tail_exit_mm": 1e3 * TAIL_EXIT_TOLERANCE,
            "expert_regrasp_deg": math.degrees(REGRASP_ANGLE),
        },
    }
    pulled = [ep["strain_mm"] for ep in episodes if ep["extracted"]]
    if pulled:  # how far off its arc the needle went in the episodes that pulled it out
        summary["median_strain_mm_extracted"] = float(np.median(pulled))
    pulls = [ep for ep in episodes if ep["extracted"] and ep["regrasp_angles_deg"]]
    if pulls:  # where the strain of a pull came from: jitter (path much longer than drift) or a straight pull
        summary["pull_strain_median_mm"] = {
            "before_regrasp_path": float(
                np.median([ep["strain_parts_mm"]["before_regrasp"][0] for ep in pulls])
            ),
            "before_regrasp_turn": float(
                np.median([ep["strain_parts_mm"]["before_regrasp"][1] for ep in pulls])
            ),
            "pull_path": float(np.median([ep["strain_parts_mm"]["pull"][0] for ep in pulls])),
            "pull_turn": float(np.median([ep["strain_parts_mm"]["pull"][1] for ep in pulls])),
            "pull_drift": float(np.median([ep["pull_drift_mm"] for ep in pulls])),
            "at_extraction": float(np.median([ep["strain_at_extraction_mm"] for ep in pulls])),
        }
    first = [ep["regrasp_angles_deg"][0] for ep in episodes if ep["regrasp_angles_deg"]]
    if first:
        summary["median_first_regrasp_deg"] = float(np.median(first))
    missed = [ep for ep in episodes if ep["let_go"] and not ep["regrasp_angles_deg"]]
    if missed:  # let go and never caught the needle again: how near the reach came to the regrasp
        closest = np.array([ep["closest_mm"] for ep in missed])
        summary["missed"] = {
            "episodes": len(missed),
            "median_closest_mm": float(np.median(closest)),
            "within_1mm": float(np.mean(closest <= 1.0)),
            "median_rotation_at_closest_deg": float(np.median([ep["closest_rotation_deg"] for ep in missed])),
        }
    attempts = [a for ep in episodes for a in ep["close_attempts"]]
    if attempts:  # why the closings before a first regrasp let the needle go
        rules = [a[0] for a in attempts]
        lodged = np.array([a[1] for a in attempts if a[0] == "lodged"])
        summary["close_attempts"] = {
            "closings": len(attempts),
            "episodes_closing": sum(bool(ep["close_attempts"]) for ep in episodes),
            "rules": {rule: rules.count(rule) for rule in sorted(set(rules))},
            "off_regrasp_median": {  # how far the jaw was from the expert's regrasp pose as it closed
                rule: {
                    "mm": float(np.median([a[2] for a in attempts if a[0] == rule])),
                    "deg": float(np.median([a[3] for a in attempts if a[0] == rule])),
                }
                for rule in sorted(set(rules))
            },
        }
        # Which way the jaw was off as it closed, and a chunk before: x, y (across the faces), z.
        summary["close_attempts"]["offset_median_mm"] = {
            rule: {
                when: [float(v) for v in np.median(np.abs([a[k] for a in attempts if a[0] == rule]), 0)]
                for when, k in (("at_closing", 4), ("a_chunk_before", 5))
            }
            for rule in sorted(set(rules))
        }
        if lodged.size:
            summary["close_attempts"]["lodged_shift_mm"] = {
                "median": float(np.median(lodged)),
                "q25": float(np.quantile(lodged, 0.25)),
                "min": float(lodged.min()),
                "within_1mm": float(np.mean(lodged <= 1.0)),
            }
    return summary


def main() -> None:
    run_nominal_seeds(TASK, "extraction_failures", __doc__.splitlines()[0], roll_out, summarize)


if __name__ == "__main__":
    main()
