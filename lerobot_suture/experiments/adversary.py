"""An unsafe "policy" for the CBF experiments: the expert, until it pulls the needle out sideways.

It runs the scripted expert until the needle has been in tissue for ``steps_in_tissue`` control
steps, then commands the jaw ``pull_distance`` metres along the phantom's lateral axis (across the
wound, orientation kept, jaw closed) and holds that target: what would tear tissue.
"""

from __future__ import annotations

import numpy as np

from lerobot_suture.expert import ScriptedExpert


class SidewaysPull:
    """``act(env) -> (10,) float32``; ``pulling`` tells whether the pull has begun."""

    def __init__(self, pull_distance: float = 0.02, steps_in_tissue: int = 3):
        if not pull_distance > 0:
            raise ValueError(f"`pull_distance` must be > 0 m. Got {pull_distance}.")
        if steps_in_tissue < 0:
            raise ValueError(f"`steps_in_tissue` must be >= 0. Got {steps_in_tissue}.")
        self.pull_distance = pull_distance
        self.steps_in_tissue = steps_in_tissue
        self.expert = ScriptedExpert()
        self.reset()

    def reset(self, env=None) -> None:
        self.expert.reset(env)
        self._in_tissue_steps = 0
        self._pull_action: np.ndarray | None = None

    @property
    def pulling(self) -> bool:
        return self._pull_action is not None

    def act(self, env) -> np.ndarray:
        u = env.unwrapped
        if self._pull_action is None and self._in_tissue_steps >= self.steps_in_tissue:
            action = self.expert.act(env).copy()
            action[:3] += self.pull_distance * u.phantom_rotation[:, 1]
            self._pull_action = action
        if self._pull_action is not None:
            return self._pull_action
        self._in_tissue_steps += int(u.needle_in_tissue)
        return self.expert.act(env)
