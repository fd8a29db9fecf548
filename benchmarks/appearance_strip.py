#!/usr/bin/env python
"""A strip of endoscope frames across the appearance options (``lerobot_suture.sim.appearance``).

The same episode (seed, expert, control step) is shown with every option off, then with each option on
alone at twice its range in ``recipes/suture_expert_randomized.yaml`` (an option the recipe leaves off, at
a tenth of its limit), then with all of them at the recipe's ranges. One seed draws the same uniform numbers for every column, so each column shows the
option's effect on one scene; the trajectory is the same in all of them.

    python benchmarks/appearance_strip.py [--out docs/appearance_strip.png] [--seed 7] [--image_size 96]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import yaml

from lerobot_suture.plotting import save_figure

RECIPE = Path(__file__).resolve().parents[1] / "recipes" / "suture_expert_randomized.yaml"
DEFAULT_OUT = Path(__file__).resolve().parents[1] / "docs" / "appearance_strip.png"


def recipe_ranges() -> dict[str, float]:
    """The appearance ranges of ``recipes/suture_expert_randomized.yaml``."""
    return dict(yaml.safe_load(RECIPE.read_text())["appearance"])


def frame(appearance: dict | None, seed: int, image_size: int, steps: int) -> np.ndarray:
    """The endoscope observation after ``steps`` expert control steps from ``reset(seed=seed)``."""
    from lerobot_suture.expert import ScriptedExpert
    from lerobot_suture.sim.suture_env import SutureEnv

    env = SutureEnv(image_size=image_size, appearance=appearance)
    expert = ScriptedExpert()
    obs, _ = env.reset(seed=seed)
    expert.reset(env)
    for _ in range(steps):
        obs, *_ = env.step(expert.act(env))
    env.close()
    return obs["pixels"]["endoscope"]


def strip_columns(seed: int = 7, image_size: int = 96, steps: int = 20) -> list[tuple[str, np.ndarray]]:
    """(label, frame) per column: off, each option alone (twice the recipe's range, within its limit; a
    tenth of its limit where the recipe leaves it off), all options at the recipe's ranges."""
    from lerobot_suture.sim.appearance import LIMITS

    ranges = recipe_ranges()
    columns = [("off", frame(None, seed, image_size, steps))]
    for name, value in ranges.items():
        alone = {name: min(2 * value, LIMITS[name][0]) if value else LIMITS[name][0] / 10}
        columns.append((f"{name}\n{alone[name]:g}", frame(alone, seed, image_size, steps)))
    columns.append(("all\n(recipe)", frame(ranges, seed, image_size, steps)))
    return columns


def appearance_strip(
    out_path: str | Path = DEFAULT_OUT,
    seed: int = 7,
    image_size: int = 96,
    steps: int = 20,
    columns: list[tuple[str, np.ndarray]] | None = None,
    title: str = "across the appearance options",
) -> Path:
    """Write the strip (``columns``, or :func:`strip_columns` of the other arguments) as a PNG of two
    labelled rows of frames; returns its path."""
    from matplotlib.figure import Figure

    columns = columns if columns is not None else strip_columns(seed, image_size, steps)
    n_cols = (len(columns) + 1) // 2
    fig = Figure(figsize=(1.25 * n_cols, 3.1), dpi=100)
    axes = fig.subplots(2, n_cols)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (label, image) in zip(axes.ravel(), columns, strict=False):
        ax.imshow(image, interpolation="nearest")
        ax.set_title(label, fontsize=7)
    fig.suptitle(
        f"Endoscope frames, one episode (seed {seed}, step {steps}), {title}",
        fontsize=8,
    )
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=0.84, wspace=0.05, hspace=0.35)
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, out_path, palette=False)
    return out_path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--image_size", type=int, default=96)
    parser.add_argument("--steps", type=int, default=20)
    args = parser.parse_args()
    path = appearance_strip(args.out, args.seed, args.image_size, args.steps)
    print(f"{path} ({path.stat().st_size / 1024:.0f} KB)")


if __name__ == "__main__":
    main()
