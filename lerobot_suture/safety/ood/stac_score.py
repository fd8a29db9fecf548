"""STAC's score, from Sentinel (Agia et al., 2024): the temporal consistency of successive action chunks. Pure
numpy; the STAC gate (:mod:`~lerobot_suture.safety.ood.chunk_consistency`) and the detector study
(:mod:`lerobot_suture.detectors.stac`) both read it.

A policy that knows what to do keeps to its plan: the part of the previous chunk that is still to come
should agree with the new chunk over the same control steps. A prediction made at control step s covers
steps s - start ... s - start + T - 1 (``start`` = n_obs_steps - 1 is the first executed index); the
previous one, made ``shift`` steps earlier, covers the same future steps s ... at indices shifted by
``shift``. The overlap is

    previous[:, start + shift : T]    and    current[:, start : T - shift]        (S samples, L steps, A)

and the score is the squared maximum mean discrepancy between the two sample sets (every member's K
chunks, flattened to L * A), as Sentinel computes it, with a Gaussian kernel
k(x, y) = exp(-||x - y||^2 / (2 b^2 L A)): the per-dimension bandwidth b is in normalized action units,
so the kernel does not saturate as the overlap grows. MMD rather than a distance of the means because the
ensemble's chunks are a distribution: a plan that splits into two modes, or whose spread jumps, is
inconsistent even when its mean stays put. The biased (V-statistic) estimate is used: it is >= 0 and
defined for any sample count, where the unbiased one can go negative on 2 to 5 samples. The first
prediction of an episode has no predecessor and scores 0.
"""

from __future__ import annotations

import numpy as np


def chunk_overlap(
    previous: np.ndarray, current: np.ndarray, shift: int, start: int
) -> tuple[np.ndarray, np.ndarray]:
    """The steps two chunks (S, T, A) predict for the same future control steps: two (S, L, A) arrays.

    Raises:
        ValueError: When the chunks do not overlap (``start + shift >= T``) or ``shift < 1``.
    """
    t_len = current.shape[-2]
    if shift < 1 or start < 0 or start + shift >= t_len:
        raise ValueError(
            f"Chunks of {t_len} steps from step {start} do not overlap after a shift of {shift} steps."
        )
    return previous[:, start + shift :], current[:, start : t_len - shift]


def mmd_squared(x: np.ndarray, y: np.ndarray, bandwidth: float) -> float:
    """Biased squared MMD of two sample sets (S, ...) and (S', ...) under a Gaussian kernel whose
    bandwidth is ``bandwidth`` per dimension (the squared distance is divided by the dimension)."""
    x = np.asarray(x, dtype=np.float64).reshape(len(x), -1)
    y = np.asarray(y, dtype=np.float64).reshape(len(y), -1)
    scale = 2.0 * bandwidth**2 * x.shape[1]

    def kernel_mean(a: np.ndarray, b: np.ndarray) -> float:
        d2 = np.sum(a**2, 1)[:, None] + np.sum(b**2, 1)[None, :] - 2.0 * a @ b.T
        return float(np.mean(np.exp(-np.maximum(d2, 0.0) / scale)))

    return max(kernel_mean(x, x) + kernel_mean(y, y) - 2.0 * kernel_mean(x, y), 0.0)
