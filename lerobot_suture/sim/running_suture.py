"""The running suture in numbers: four entry-and-exit pairs marked along the wound, and the marks added to the
scene for them.

The wound runs along the phantom's y axis (``assets/scene.xml``); each pair crosses it as the single
insertion's does, entry at x = -8 mm, exit at x = +8 mm (phantom frame), the pairs :data:`PAIR_SPACING` apart
along the wound, centred on it. A throw is one pair: insert the needle from its entry to its exit point,
extract it through the exit hole, regrasp it at its tail, and go on to the next pair. Each throw is scored as
an insertion is (``task.ENTRY_TOLERANCE``, ``task.EXIT_TOLERANCE``); each extraction as ``extraction`` scores
one (its strain counted from the start of the extraction).
"""

from __future__ import annotations

import mujoco
import numpy as np

N_THROWS = 4
PAIR_SPACING = 0.006
"""Distance between neighbouring pairs along the wound (m)."""
PAIR_HALF_WIDTH = 0.008
"""Distance of each entry and exit point from the wound line (m), as the single insertion's."""


def pair_points(throw: int) -> tuple[np.ndarray, np.ndarray]:
    """(entry (3,), exit (3,)) of throw ``throw`` (0-based) in the phantom frame (m)."""
    if not 0 <= throw < N_THROWS:
        raise ValueError(f"`throw` must be in [0, {N_THROWS}). Got {throw}.")
    y = (throw - (N_THROWS - 1) / 2) * PAIR_SPACING
    return np.array([-PAIR_HALF_WIDTH, y, 0.0]), np.array([PAIR_HALF_WIDTH, y, 0.0])


def add_suture_marks(spec: mujoco.MjSpec) -> None:
    """Mark the four pairs on the phantom of a scene spec: the single insertion's marks (and its entry and
    exit sites) move to the first pair, and three more pairs of the same look are added."""
    phantom = spec.body("phantom")
    entry_marker, exit_marker = spec.geom("entry_marker"), spec.geom("exit_marker")
    for throw in range(N_THROWS):
        entry, exit_ = pair_points(throw)
        if throw == 0:
            entry_marker.pos[:2], exit_marker.pos[:2] = entry[:2], exit_[:2]
            spec.site("entry_point").pos[:2], spec.site("exit_point").pos[:2] = entry[:2], exit_[:2]
            continue
        for name, marker, point in (("entry", entry_marker, entry), ("exit", exit_marker, exit_)):
            geom = phantom.add_geom()
            geom.name = f"{name}_marker_{throw}"
            geom.type = marker.type
            geom.size = marker.size
            geom.material = marker.material
            geom.contype, geom.conaffinity, geom.group = 0, 0, marker.group
            geom.pos = [point[0], point[1], marker.pos[2]]
