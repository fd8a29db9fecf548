"""What the arc guard does to the tissue: strain with and without it, the expert's insertion jittered.

The scripted expert drives the needle in; from ``--lead`` control steps after the needle enters the tissue, every
jaw target it gives is jittered by Gaussian noise of ``sigma`` (m, per axis) for ``--steps`` steps, with and
without ``arc_guard`` (``lerobot_suture.safety.arc_guard``), on the same seeds. Prints one JSON object: per sigma
and seed the strain (mm, the env's ``tissue_strain`` over the jittered steps) each way, and whether the needle
was still in the tissue at the end::

    .venv/bin/python benchmarks/arc_guard.py [--seeds 3 4 5] [--sigmas 0 0.0005 0.002 0.02 0.05] [--output F]
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")


def jittered_strain(
    arc_guard: bool, sigma: float, seed: int, steps: int = 15, lead: int = 5
) -> tuple[float, bool]:
    """Tissue strain (m) over ``steps`` control steps of the expert's insertion on ``seed``, its jaw targets
    jittered by ``sigma`` (m) per axis from ``lead`` steps after the needle enters the tissue; and whether the
    needle is still in the tissue at the end (a jitter that tears it out ends the count there)."""
    import gymnasium as gym
    import numpy as np

    import lerobot_suture  # noqa: F401
    from lerobot_suture.expert import ScriptedExpert

    env = gym.make(
        "lerobot_suture/NeedleInsertion-v0", obs_type="pixels_agent_pos", image_size=32, arc_guard=arc_guard
    )
    env.reset(seed=seed)
    expert, u = ScriptedExpert(), env.unwrapped
    expert.reset(env)
    info = {"tissue_strain": 0.0}
    for _ in range(100):
        if u.needle_in_tissue:
            break
        _, _, _, _, info = env.step(expert.act(env))
    for _ in range(lead):  # jitter right at the entry would pull the tip back out, beyond the guard
        _, _, _, _, info = env.step(expert.act(env))
    if not (u.needle_in_tissue and u.needle_grasped):
        raise RuntimeError(
            f"Seed {seed}: the expert's needle is not held in the tissue {lead} steps after entry."
        )
    start, rng = info["tissue_strain"], np.random.default_rng(seed)
    for _ in range(steps):
        action = expert.act(env).copy()
        action[:3] += rng.normal(0.0, sigma, 3)
        _, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break
    in_tissue = bool(u.needle_in_tissue)
    env.close()
    return float(info["tissue_strain"] - start), in_tissue


def main() -> None:
    from _report import emit, machine  # beside this script (tests load ``jittered_strain`` alone)

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[3, 4, 5])
    parser.add_argument("--sigmas", type=float, nargs="+", default=[0.0, 0.0005, 0.002, 0.02, 0.05])
    parser.add_argument("--steps", type=int, default=15)
    parser.add_argument("--lead", type=int, default=5)
    parser.add_argument("--output", type=Path)
    args = parser.parse_args()
    rows = []
    for sigma in args.sigmas:
        for seed in args.seeds:
            row = {"sigma_m": sigma, "seed": seed}
            for name, guard in (("free", False), ("guarded", True)):
                strain, in_tissue = jittered_strain(guard, sigma, seed, args.steps, args.lead)
                row[f"{name}_strain_mm"], row[f"{name}_in_tissue"] = round(1e3 * strain, 3), in_tissue
            rows.append(row)
    emit(
        {
            "benchmark": "arc_guard",
            "steps": args.steps,
            "lead": args.lead,
            "rows": rows,
            "machine": machine(),
        },
        args.output,
    )


if __name__ == "__main__":
    main()
