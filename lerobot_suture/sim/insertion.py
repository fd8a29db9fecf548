"""Progress of a needle insertion: where the needle tip entered and emerged from the tissue, how far
from the marked entry and exit points, how far it protrudes, and how much tissue the needle strained.

The env's termination and success rules (``suture_env``, Episode End) read these measurements. Points
are in the phantom frame (``tissue``) unless named world; lengths in metres.
"""

from __future__ import annotations

import math

import numpy as np

from lerobot_suture.sim import tissue
from lerobot_suture.sim.geometry import NEEDLE_RADIUS


class InsertionProgress:
    """The needle's passage through the tissue pad in one episode, updated once per control step.

    Args:
        arc_local: (n, 3) points along the needle's arc in the needle frame, the tip first (m).
        entry_local: (3,) the marked entry point in the phantom frame (m).
        exit_local: (3,) the marked exit point in the phantom frame (m).

    Attributes:
        in_tissue: Some point of the needle's arc is inside the pad.
        first_in_tissue_step: Control step at which the needle first touched tissue, or None.
        entry_error: Distance in the tissue surface from the entry point to where the tip went in (m);
            inf until it has.
        exit_error: The same for the exit point and where the tip came out (m); inf until it has.
        tail_exit_error: Distance in the tissue surface from the exit point to where the needle's tail left
            the tissue (m): the end of an extraction through the exit hole; inf until it has.
        strain: Accumulated off-arc motion of the needle in tissue (m).
        tip_world: (3,) the needle tip in the world frame at the last update (m); None before it.
    """

    def __init__(self, arc_local: np.ndarray, entry_local: np.ndarray, exit_local: np.ndarray):
        self._arc_local = arc_local
        self._entry_local = entry_local
        self._exit_local = exit_local
        self.in_tissue = False
        self.first_in_tissue_step: int | None = None
        self.entry_error = math.inf
        self.exit_error = math.inf
        self.tail_exit_error = math.inf
        self.strain = 0.0
        self.tip_world: np.ndarray | None = None
        self._tip_inside = False
        self._tail_inside = False
        self._entry_location: np.ndarray | None = None
        self._exit_location: np.ndarray | None = None
        self._prev_tip_local: np.ndarray | None = None
        self._prev_tail_local: np.ndarray | None = None
        self._prev_needle_local: tuple[np.ndarray, np.ndarray] | None = None

    def update(
        self,
        centre: np.ndarray,
        rotation: np.ndarray,
        phantom_position: np.ndarray,
        phantom_rotation: np.ndarray,
        step_index: int,
        first: bool = False,
    ) -> None:
        """Record the needle's pose after a control step (or at reset, with ``first``: no crossing yet).

        Args:
            centre: (3,) needle centre, world (m).
            rotation: (3, 3) needle orientation, world.
            phantom_position: (3,) centre of the pad's top surface, world (m).
            phantom_rotation: (3, 3) world-from-phantom rotation.
            step_index: Control steps taken since reset.
            first: The episode's first pose: only where the needle is, no surface crossing or strain.
        """
        inv = phantom_rotation.T
        centre_local = inv @ (centre - phantom_position)
        rot_local = inv @ rotation
        arc = centre_local + self._arc_local @ rot_local.T  # (n, 3) phantom frame
        inside = tissue.inside_pad(arc)
        tip_local = arc[0]
        was_in_tissue = self.in_tissue
        self.in_tissue = bool(inside.any())
        if self.in_tissue and self.first_in_tissue_step is None:
            self.first_in_tissue_step = step_index
        tip_inside = bool(inside[0])
        tail_inside = bool(inside[-1])
        if not first and self._prev_tip_local is not None:
            if tip_inside and not self._tip_inside and self._entry_location is None:
                self._entry_location = tissue.surface_crossing(self._prev_tip_local, tip_local)
                self.entry_error = float(np.linalg.norm(self._entry_location[:2] - self._entry_local[:2]))
            elif not tip_inside and self._tip_inside and self._entry_location is not None:
                if self._exit_location is None:
                    self._exit_location = tissue.surface_crossing(self._prev_tip_local, tip_local)
                    self.exit_error = float(np.linalg.norm(self._exit_location[:2] - self._exit_local[:2]))
            if self._tail_inside and not tail_inside and self._prev_tail_local is not None:
                crossing = tissue.surface_crossing(self._prev_tail_local, arc[-1])
                self.tail_exit_error = float(np.linalg.norm(crossing[:2] - self._exit_local[:2]))
            if (self.in_tissue or was_in_tissue) and self._prev_needle_local is not None:
                translation, rotation_off = tissue.off_arc_motion(
                    *self._prev_needle_local, centre_local, rot_local, NEEDLE_RADIUS
                )
                self.strain += translation + rotation_off
        self._tip_inside = tip_inside
        self._tail_inside = tail_inside
        self._prev_tip_local = tip_local
        self._prev_tail_local = arc[-1]
        self._prev_needle_local = (centre_local, rot_local)
        self.tip_world = phantom_position + phantom_rotation @ tip_local

    @property
    def extracted(self) -> bool:
        """The needle went into the tissue and is all out of it again."""
        return self.first_in_tissue_step is not None and not self.in_tissue

    @property
    def protrusion(self) -> float:
        """Distance of the needle tip beyond where it emerged (m); 0 until it has, or while back inside."""
        if self._exit_location is None or self._tip_inside:
            return 0.0
        return float(np.linalg.norm(self._prev_tip_local - self._exit_location))
