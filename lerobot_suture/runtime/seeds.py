"""Episode seeds: every group of runs (a scenario, an arm, a part of a benchmark) has its own range.

Recording seeds start at 0, calibration's fresh seeds at :data:`FRESH_SEED_BASE`, and each command's
test or validation seeds at its own ``--seed`` base, so no seed is used twice for two purposes.
"""

from __future__ import annotations

SEED_STRIDE = 10_000
"""Distance between the first seeds of two groups under one base: groups never overlap."""
FRESH_SEED_BASE = 1_000_000
"""First of the fresh seeds used when no dataset gives validation seeds (far from recording seeds)."""


def episode_seeds(base: int, group: int, n: int) -> list[int]:
    """The seeds of ``n`` episodes of one group (a scenario, an arm) under the base seed ``base``."""
    if n > SEED_STRIDE:
        raise ValueError(f"A group holds at most {SEED_STRIDE} episodes. Got {n}.")
    return [base + group * SEED_STRIDE + k for k in range(n)]


def fresh_seeds(n: int, start: int = 0) -> list[int]:
    """``n`` fresh seeds, the ``start``-th onwards (no recording or test seed is among them)."""
    return [FRESH_SEED_BASE + k for k in range(start, start + n)]
