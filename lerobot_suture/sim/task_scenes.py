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
from lerobot_suture.sim.pickup import resting_needle_pose
from lerobot_suture.sim.psm import ARM_JOINTS
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
        if self.task_name == "pickup" and not self._grasp.held and not self._grasp.resting:
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
        # insertion: the throw is over once the tip protrudes MIN_PROTRUSION beyond where it emerged, the
        # needle still spanning the wound; on the marks if it entered and emerged within tolerance.
        over = bool(progress.protrusion >= MIN_PROTRUSION and progress.in_tissue)
        on_marks = progress.entry_error <= ENTRY_TOLERANCE and progress.exit_error <= EXIT_TOLERANCE
        return over, bool(over and on_marks)
