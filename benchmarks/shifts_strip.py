#!/usr/bin/env python
"""A strip of endoscope frames under each shift (``lerobot_suture.sim.shifts``) at its default magnitudes.

The same episode (seed, expert, control step) with no shift, then under every shift at each of its two
default magnitudes. Shifts that leave the image alone (state noise, action delay) are shown too: their
frames differ only through where the arm went.

    python benchmarks/shifts_strip.py [--out docs/shifts_strip.png] [--seed 7] [--image_size 96]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from appearance_strip import appearance_strip

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "docs" / "shifts_strip.png"


def frame(shift, seed: int, image_size: int, steps: int) -> np.ndarray:
    """The endoscope observation after ``steps`` expert control steps from ``reset(seed=seed)``."""
    import gymnasium as gym

    from lerobot_suture import ENV_ID
    from lerobot_suture.expert import ScriptedExpert
    from lerobot_suture.sim.shifts import ShiftWrapper

    env = gym.make(ENV_ID, disable_env_checker=True, image_size=image_size)
    env = env if shift is None else ShiftWrapper(env, shift)
    expert = ScriptedExpert()
    obs, _ = env.reset(seed=seed)
    expert.reset(env)
    for _ in range(steps):
        obs, *_ = env.step(expert.act(env))
    env.close()
    return obs["pixels"]["endoscope"]


def main() -> None:
    from lerobot_suture.sim.shifts import default_shifts

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--image_size", type=int, default=96)
    parser.add_argument("--steps", type=int, default=20)
    args = parser.parse_args()
    columns = [("none", frame(None, args.seed, args.image_size, args.steps))]
    columns += [
        (s.label.replace("@", "\n"), frame(s, args.seed, args.image_size, args.steps))
        for s in default_shifts()
    ]
    path = appearance_strip(
        args.out, args.seed, args.image_size, args.steps, columns, "under each shift at its two magnitudes"
    )
    print(f"{path} ({path.stat().st_size / 1024:.0f} KB)")


if __name__ == "__main__":
    main()
