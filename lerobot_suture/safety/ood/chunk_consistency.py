"""The detector for any LeRobot policy that predicts action chunks: STAC on the chunks it actually predicts.

An ensemble's gate reads its members' covariance; ACT, diffusion and other single-model policies have none.
What every chunking policy has is its chunks. :class:`ChunkCapture` keeps each chunk a policy predicts (it wraps
the instance's ``predict_action_chunk``, the one method LeRobot's ``select_action`` and ``lerobot-rollout``'s
inference engines call for a new chunk), and :class:`ChunkConsistencyMonitor` scores it against the previous
one with STAC (:mod:`lerobot_suture.safety.ood.stac_score`: the squared MMD of the overlapping steps, in the policy's
normalized action space). The monitor is a :class:`~lerobot_suture.safety.ood.gate.ChunkDetector`: the one gate
(:class:`~lerobot_suture.safety.ood.gate.ChunkGate`) tests its scores as it tests the ensemble's, on the episode's
running maximum against :class:`~lerobot_suture.safety.ood.calibration_file.StacCalibration`.
"""

from __future__ import annotations

import numpy as np

from lerobot_suture.safety.ood.stac_score import chunk_overlap, mmd_squared


class ChunkCapture:
    """Keeps the chunks a policy predicts: wraps ``owner.<method>`` (by default the policy's
    ``predict_action_chunk``) on the instance.

    ``chunks`` counts the predictions; ``last`` is the last chunk as (B, T, A) float64 numpy in the policy's
    normalized action space (None before the first). ``release()`` restores the method.
    """

    def __init__(self, owner, method: str = "predict_action_chunk"):
        if not callable(getattr(owner, method, None)):
            raise TypeError(
                f"{type(owner).__name__} has no `{method}`: the chunk gate needs a policy that predicts action "
                "chunks (ACT, diffusion, ensemble_diffusion, ...)."
            )
        self._owner, self._method = owner, method
        self._inner = getattr(owner, method)
        self.chunks = 0
        self.last: np.ndarray | None = None

        def capture(*args, **kwargs):
            chunk = self._inner(*args, **kwargs)
            self.last = chunk.detach().float().cpu().numpy().astype(np.float64)
            self.chunks += 1
            return chunk

        setattr(owner, method, capture)

    def release(self) -> None:
        setattr(self._owner, self._method, self._inner)


def chunk_source(policy) -> tuple[object, str, int]:
    """Where a policy's full chunks come from: (object, method name, index in the chunk of the first executed step).

    LeRobot's diffusion returns only the executed steps from ``predict_action_chunk``; its whole horizon comes
    from ``diffusion.conditional_sample``. Others (ACT, ...) return the whole chunk from ``predict_action_chunk``.
    """
    inner = getattr(policy, "diffusion", None)
    if inner is not None and callable(getattr(inner, "conditional_sample", None)):
        return inner, "conditional_sample", int(policy.config.n_obs_steps) - 1
    return policy, "predict_action_chunk", 0


class ChunkConsistencyMonitor:
    """STAC between each new chunk and the one before it, over one episode (batch element 0).

    Args:
        shift: control steps between two successive chunks (the policy's ``n_action_steps`` under
            synchronous inference).
        start: index in the chunk of the first executed step (``n_obs_steps - 1`` for diffusion, 0 for ACT).
        bandwidth: the kernel's per-dimension bandwidth (normalized action units).
    """

    def __init__(self, shift: int, start: int = 0, bandwidth: float = 0.5):
        if shift < 1 or start < 0 or not bandwidth > 0:
            raise ValueError(
                f"Need shift >= 1, start >= 0, bandwidth > 0. Got {shift}, {start}, {bandwidth}."
            )
        self.shift, self.start, self.bandwidth = int(shift), int(start), float(bandwidth)
        self.reset()

    def reset(self) -> None:
        self._previous: np.ndarray | None = None

    def score(self, chunk: np.ndarray) -> float:
        """Score a new chunk (B, T, A) or (T, A) against the previous one; the first of an episode scores 0."""
        current = np.asarray(chunk, dtype=np.float64)
        current = current[:1] if current.ndim == 3 else current[None]
        score = 0.0
        if self._previous is not None and self.start + self.shift < current.shape[1]:
            a, b = chunk_overlap(self._previous, current, self.shift, self.start)
            score = mmd_squared(a, b, self.bandwidth)
        self._previous = current
        return score
