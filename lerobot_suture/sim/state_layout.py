"""What a registered ``environment_state`` holds: the parts a real system measures or plans, in the order the env
stacks them, each combination told apart by its size alone.

The parts are the current throw's marks (``marks=True``, :mod:`lerobot_suture.sim.wound_marks`), the high level's
subtask and throw (``subtask=True``, :mod:`lerobot_suture.sim.subtasks`) and the regrasp planned through the marks
(``regrasp_target=True``, :mod:`lerobot_suture.sim.regrasp_target`). Every non-empty combination has a size of its
own, so a policy's ``observation.environment_state`` shape names the flags it was recorded with; any other size is
the privileged simulator state.
"""

from __future__ import annotations

import itertools

import numpy as np

from lerobot_suture.sim.regrasp_target import REGRASP_TARGET_DIM
from lerobot_suture.sim.subtasks import SUBTASK_DIM
from lerobot_suture.sim.wound_marks import MARKS_DIM

STATE_PARTS: dict[str, int] = {
    "marks": MARKS_DIM,
    "subtask": SUBTASK_DIM,
    "regrasp_target": REGRASP_TARGET_DIM,
}
"""Each part's name (the env's flag) and size, in the order the env stacks them."""


def state_size(parts) -> int:
    """Entries of an ``environment_state`` holding ``parts`` (names of :data:`STATE_PARTS`)."""
    return sum(STATE_PARTS[name] for name in parts)


LAYOUTS: dict[int, tuple[str, ...]] = {
    state_size(chosen): chosen
    for flags in itertools.product((False, True), repeat=len(STATE_PARTS))
    if (chosen := tuple(name for name, on in zip(STATE_PARTS, flags, strict=True) if on))
}
"""Size -> the parts an ``environment_state`` of that size holds (every non-empty combination)."""
PRIVILEGED_STATE_DIM = 18
"""Entries of the privileged simulator state (``obs_type`` with ``state``), which no combination may share."""
if len(LAYOUTS) != 2 ** len(STATE_PARTS) - 1 or PRIVILEGED_STATE_DIM in LAYOUTS:
    raise RuntimeError(f"The registered parts' sizes {LAYOUTS} do not tell the combinations apart.")


def state_parts(size: int) -> tuple[str, ...] | None:
    """The parts a registered ``environment_state`` of ``size`` entries holds; ``()`` for 0, None for a size that is
    no combination (the privileged state)."""
    return () if size == 0 else LAYOUTS.get(size)


def part_slices(parts) -> dict[str, slice]:
    """Where each of ``parts`` lies in an ``environment_state`` that holds exactly them."""
    slices, start = {}, 0
    for name in STATE_PARTS:
        if name in parts:
            slices[name] = slice(start, start + STATE_PARTS[name])
            start += STATE_PARTS[name]
    return slices


def registered_parts(env_state) -> dict | None:
    """Name -> the part (..., n) of a registered ``environment_state`` (parts along its last axis; an array or a
    tensor): ``{}`` for None, None for the privileged state."""
    if env_state is None:
        return {}
    parts = state_parts(np.shape(env_state)[-1])
    if parts is None:
        return None
    return {name: env_state[..., where] for name, where in part_slices(parts).items()}


def registered_marks(env_state):
    """The marks (..., 6) in a registered ``environment_state``, or None where it holds none (or is the privileged
    state, or None)."""
    return (registered_parts(env_state) or {}).get("marks")
