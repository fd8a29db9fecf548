"""How each task of the family sets up its scene at reset and judges where a step left it.

A mixin of :class:`~lerobot_suture.sim.suture_env.SutureEnv`: it reads and writes the env's scene handles
(the arm, the grasp, the insertion's progress) after the phantom is placed; the numbers live in ``task``
(insertion), ``pickup`` and ``extraction``. Every draw comes from the env's ``np_random``, in a fixed order
per task, so a seed gives one scene.
"""

from __future__ import annotations

import mujoco
import numpy as np

from lerobot_suture.sim.extraction import extraction_succeeded, start_drive_angle, throw_sweep
from lerobot_suture.sim.geometry import jaw_holding
from lerobot_suture.sim.grasp import JAW_OPEN_ANGLE
from lerobot_suture.sim.insertion import InsertionProgress
from lerobot_suture.sim.pickup import resting_needle_pose
from lerobot_suture.sim.psm import ARM_JOINTS
from lerobot_suture.sim.running_suture import N_THROWS, pair_points
from lerobot_suture.sim.task import (
    ARM_START_NOISE,
    ENTRY_TOLERANCE,
    EXIT_TOLERANCE,
    GRASP_ANGLE,
    GRASP_RANGES,
    MIN_PROTRUSION,
)

RESTING_CLEARANCE = 0.001
RESTING_SPEED = 0.001
"""A dropped needle rests on the phantom (``grasp.NeedleGrasp.rest``) once its lowest point is within
``RESTING_CLEARANCE`` (m) of the tissue surface and its centre slower than ``RESTING_SPEED`` (m/s)."""


class TaskScenes:
    """The task-dependent part of ``reset`` and ``step``."""

    def _start_throw(self, throw: int) -> None:
        """Begin throw ``throw`` (0-based): its entry and exit points, a fresh record of the needle's passage."""
        self._throw = throw
        self._throw_phase = "insert"
        self._extraction_strain_start = 0.0
        if self.task_name == "running_suture":
            if throw == 0:
                self._throw_results: list[dict] = []
            self._entry_local, self._exit_local = pair_points(throw)
        self._progress = InsertionProgress(self._arc_local, self._entry_local, self._exit_local)

    def _task_info(self) -> dict:
        """Info entries of the task's own: the running suture's throw and its per-throw record."""
        if self.task_name != "running_suture":
            return {}
        results = self._throw_results
        return {
            "throw_index": self._throw,
            "throw_phase": self._throw_phase,
            "throws_on_marks": sum(r["on_marks"] for r in results),
            "throws_extracted": sum(r["extracted"] for r in results),
            "throw_results": [dict(r) for r in results],
        }

    def _set_up_task(self, rng: np.random.Generator) -> None:
        """Place the needle and the arm for this episode's task (the phantom is placed already)."""
        if self.task_name == "pickup":
            centre, rotation = resting_needle_pose(
                rng, self._phantom_pos, self._phantom_rot, 0.5 * self._grasp.wire_diameter
            )
            self._grasp.place_free_needle(self.data, centre, rotation)
        else:
            angle_range, offset_range, roll_range = GRASP_RANGES[self.grasp]
            angle = GRASP_ANGLE + rng.uniform(-1, 1) * angle_range
            offset = rng.uniform(-1, 1) * offset_range
            self._grasp.set(angle, offset, rng.uniform(-1, 1) * roll_range)
        if self.task_name == "extraction":
            self._set_up_finished_throw(rng)
            return
        qpos = self._home_qpos + rng.uniform(-1, 1, size=len(ARM_JOINTS)) * ARM_START_NOISE
        self.data.qpos[self._arm.qpos] = qpos
        held = self._grasp.held
        self.data.qpos[self._grasp.jaw_qpos] = self._grasp.held_jaw_angle() if held else JAW_OPEN_ANGLE
        mujoco.mj_forward(self.model, self.data)
        if held:
            self._grasp.snap_needle(self.data)

    def _set_up_finished_throw(self, rng: np.random.Generator) -> None:
        """The end of an insertion: the needle driven through, held at its tail (``extraction``)."""
        frame = self.insertion_frame()
        drive = start_drive_angle(rng, frame.exit_angle)
        target = jaw_holding(frame.centre, frame.needle_rotation(drive), *self.grasp_in_jaw)
        self.data.qpos[self._arm.qpos] = self._home_qpos
        self.data.qpos[self._arm.qpos] = self._arm.solve_jaw_pose(self.data, *target)
        self.data.qpos[self._grasp.jaw_qpos] = self._grasp.held_jaw_angle()
        mujoco.mj_forward(self.model, self.data)
        self._grasp.snap_needle(self.data)
        # The insertion's record (where the tip went in and came out) from poses along the throw.
        for k, angle in enumerate(throw_sweep(drive)):
            self._progress.update(
                frame.centre,
                frame.needle_rotation(angle),
                self._phantom_pos,
                self._phantom_rot,
                0,
                first=k == 0,
            )
        # The needle where the arm's kinematics put it, as every later step sees it.
        self._progress.update(*self.needle_pose(), self._phantom_pos, self._phantom_rot, 0)

    def _after_physics(self) -> None:
        """After a control step's physics: a dropped needle lying still on the phantom rests there."""
        needs_picking_up = self.task_name in ("pickup", "running_suture")
        if needs_picking_up and not self._grasp.held and not self._grasp.resting:
            still = self._grasp.needle_speed(self.data) < RESTING_SPEED
            if still and self.needle_clearance < RESTING_CLEARANCE:
                self._grasp.rest(self.data)

    def _task_outcome(self) -> tuple[bool, bool]:
        """(terminated, success) after a control step."""
        progress = self._progress
        if self.task_name == "pickup":
            success = self.needle_picked_up
            return success, success
        if self.task_name == "extraction":
            success = extraction_succeeded(
                self._grasp.held, progress.extracted, progress.tail_exit_error, progress.strain
            )
            return success, success
        if self.task_name == "running_suture":
            return self._running_suture_outcome()
        # insertion: the throw is over once the tip protrudes MIN_PROTRUSION beyond where it emerged, the
        # needle still spanning the wound; on the marks if it entered and emerged within tolerance.
        over = bool(progress.protrusion >= MIN_PROTRUSION and progress.in_tissue)
        on_marks = progress.entry_error <= ENTRY_TOLERANCE and progress.exit_error <= EXIT_TOLERANCE
        return over, bool(over and on_marks)

    def _running_suture_outcome(self) -> tuple[bool, bool]:
        """(terminated, success) of a running suture: it ends on a throw off the marks or when the last throw
        is over; it succeeds when all four were on the marks. A throw on the marks goes on to its extraction,
        and an extraction that is done starts the next throw."""
        progress = self._progress
        if self._throw_phase == "insert":
            if not (progress.protrusion >= MIN_PROTRUSION and progress.in_tissue):
                return False, False
            on_marks = bool(progress.entry_error <= ENTRY_TOLERANCE and progress.exit_error <= EXIT_TOLERANCE)
            self._throw_results.append(
                {
                    "throw": self._throw,
                    "entry_error_m": float(progress.entry_error),
                    "exit_error_m": float(progress.exit_error),
                    "on_marks": on_marks,
                    "over_step": self._step_index,
                    "extracted": False,
                }
            )
            if not on_marks or self._throw == N_THROWS - 1:
                return True, on_marks and all(r["on_marks"] for r in self._throw_results)
            self._throw_phase = "extract"
            self._extraction_strain_start = progress.strain
            return False, False
        strain = progress.strain - self._extraction_strain_start
        if extraction_succeeded(self._grasp.held, progress.extracted, progress.tail_exit_error, strain):
            self._throw_results[-1]["extracted"] = True
            self._throw_results[-1]["extraction_strain_m"] = float(strain)
            self._start_throw(self._throw + 1)
            self._progress.update(
                *self.needle_pose(), self._phantom_pos, self._phantom_rot, self._step_index, True
            )
        return False, False
