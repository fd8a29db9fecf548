"""One control step of the instrument arm: from a target jaw pose to the physics steps that move it.

The target becomes a Cartesian velocity command (reach it in one control step, speed-limited), expressed at
the needle tip while the needle is held; the tip's linear velocity passes through the env's
``tip_velocity_filter`` (the one point where a safety filter such as the CBF acts); inverse kinematics at
the tip turns the twist into joint velocities, which the arm's velocity actuators track at physics rate,
the tissue resisting the needle's motion while it is in tissue. Units: m, rad, s.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np

from lerobot_suture.sim import controller, tissue
from lerobot_suture.sim.geometry import matrix_from_rot6
from lerobot_suture.sim.grasp import NeedleGrasp
from lerobot_suture.sim.psm import (
    IK_UPDATES_WHEN_FILTERED,
    MAX_ANGULAR_SPEED,
    MAX_LINEAR_SPEED,
    PSM,
    SEGMENT_TRACKING_GAIN,
    TIME_TO_TARGET,
)

MAX_TURN_RATE_IN_TISSUE = 1.0
"""The fastest turn (rad/s) the arc guard passes: the arm's twist is solved once per control step, and the path of a
faster turn strays further from the arc (the expert drives at 0.6)."""
TipVelocityFilter = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""f(needle_tip_pos (3,) m, v_nominal (3,) m/s) -> v_safe (3,) m/s."""


@dataclass
class DriveResult:
    """What one control step commanded.

    Attributes:
        v_nominal: (3,) m/s velocity of the driven point (the needle tip while held, else the jaw tip)
            before the filter.
        v_command: (3,) m/s the same after the filter (``v_nominal`` when none acts).
        tip_trace: (n_substeps, 3) m needle tip after every physics step, or None when not recorded.
    """

    v_nominal: np.ndarray
    v_command: np.ndarray
    tip_trace: np.ndarray | None


class InstrumentDrive:
    """Moves the arm towards a target jaw pose over one control step of ``n_substeps`` physics steps.

    Args:
        model, data: The scene's MuJoCo model and data.
        arm: The arm's joints and inverse kinematics.
        grasp: The needle in the jaw.
        tip_local: (3,) m the needle tip in the needle frame.
        n_substeps: Physics steps per control step.

    Attributes:
        needle_on_arc: while the held needle is in tissue, replace each step's target by the pose on the
            needle's arc nearest to it (``tissue.arc_target``: the jaw turned about the needle's own centre, by
            at most ``MAX_TURN_RATE_IN_TISSUE`` over the step), before any tip velocity filter: the guard of
            ``safety.arc_guard.NeedleArcGuard``. In the world frame: a moving phantom's own motion is not taken
            out.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        arm: PSM,
        grasp: NeedleGrasp,
        tip_local: np.ndarray,
        n_substeps: int,
    ):
        self._model, self._data = model, data
        self._arm, self._grasp = arm, grasp
        self._tip_local = tip_local
        self._n_substeps = n_substeps
        self._physics_dt = float(model.opt.timestep)
        self.needle_on_arc = False

    def step(
        self,
        target: np.ndarray,
        tip_velocity_filter: TipVelocityFilter | None,
        in_tissue: bool,
        record_trace: bool,
        tip_tracking: bool = False,
        place_phantom: Callable[[float], None] | None = None,
    ) -> DriveResult:
        """Run one control step towards ``target`` (10,) (the action's layout; already validated).

        ``in_tissue``: whether the needle is in tissue as the step begins (the tissue resists then).
        ``tip_tracking``: while the needle is held, drive its tip in a straight line to where the target pose
        puts it (speed-limited along that line), with the tip-first solve and segment feedback a filter gets:
        the Cartesian controller a safety step outside the env (the robot path's ``suture_cbf``) relies on.
        ``place_phantom``: None while the phantom stands still, else called before every physics step with the
        time (s) from the start of the control step to the end of that physics step, to place the phantom there.
        Raises ``ValueError`` when the filter returns anything but a finite (3,) velocity.
        """
        m, d, grasp = self._model, self._data, self._grasp
        grasp.command_jaw(d, float(target[9]), in_tissue=in_tissue)

        filtered = grasp.held and (tip_velocity_filter is not None or tip_tracking)
        if filtered:
            # MuJoCo's stored kinematics are one physics step old after mj_step; the filter must see
            # where the tip is, since its segment starts there.
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
        jaw_pos, jaw_rot = self._arm.jaw_pose(d)
        target_pos, target_rot = target[:3], matrix_from_rot6(target[3:9])
        if self.needle_on_arc and in_tissue and grasp.held:
            target_pos, target_rot = tissue.arc_target(
                jaw_pos + jaw_rot @ grasp.position,
                jaw_rot @ grasp.rotation[:, 2],
                jaw_pos,
                jaw_rot,
                self._held_tip(jaw_pos, jaw_rot),
                self._held_tip(target_pos, target_rot),
                MAX_TURN_RATE_IN_TISSUE * TIME_TO_TARGET,
            )
        linear, angular = controller.pose_velocity_command(
            jaw_pos, jaw_rot, target_pos, target_rot, TIME_TO_TARGET, MAX_LINEAR_SPEED, MAX_ANGULAR_SPEED
        )
        if grasp.held:
            point = self._held_tip(jaw_pos, jaw_rot)
            if tip_tracking:
                v_nominal = controller.limit_speed(
                    (self._held_tip(target_pos, target_rot) - point) / TIME_TO_TARGET, MAX_LINEAR_SPEED
                )
            else:
                v_nominal = controller.point_velocity(linear, angular, jaw_pos, point)
            v_command = v_nominal
            if tip_velocity_filter is not None:
                v_command = np.asarray(tip_velocity_filter(point.copy(), v_nominal.copy()), dtype=np.float64)
                if v_command.shape != (3,) or not np.all(np.isfinite(v_command)):
                    raise ValueError(
                        f"`tip_velocity_filter` must return a finite (3,) velocity. Got {v_command!r}."
                    )
        else:
            point, v_nominal = jaw_pos, linear
            v_command = linear

        # While a safety filter shapes the tip's velocity, the tip must follow the filtered straight
        # segment (the CBF's guarantee rests on it): the command is re-solved several times per control
        # step by tip-first IK (``controller.tip_first_velocity_ik``), with feedback towards where the
        # segment says the tip should be by now; otherwise one plain solve per step is enough.
        blocks = IK_UPDATES_WHEN_FILTERED if filtered else 1
        substeps = self._n_substeps // blocks
        trace = np.empty((self._n_substeps, 3)) if record_trace else None
        segment_start = point.copy()
        for block in range(blocks):
            if block > 0:
                mujoco.mj_kinematics(m, d)
                mujoco.mj_comPos(m, d)
                jaw_pos, jaw_rot = self._arm.jaw_pose(d)
                point = self._held_tip(jaw_pos, jaw_rot)
            if filtered:
                elapsed = block * substeps * self._physics_dt
                v_track = v_command + SEGMENT_TRACKING_GAIN * (segment_start + v_command * elapsed - point)
                self._actuate(point, v_track, angular, jaw_pos, jaw_rot, in_tissue, tip_first=True)
            else:
                self._actuate(point, v_command, angular, jaw_pos, jaw_rot, in_tissue, tip_first=False)
            if trace is not None or place_phantom is not None:
                for k in range(block * substeps, (block + 1) * substeps):
                    if place_phantom is not None:
                        place_phantom((k + 1) * self._physics_dt)
                    mujoco.mj_step(m, d)
                    if trace is None:
                        continue
                    mujoco.mj_kinematics(m, d)  # the tip after this physics step, not before it
                    centre, rotation = grasp.needle_pose(d)
                    trace[k] = centre + rotation @ self._tip_local
            else:
                mujoco.mj_step(m, d, nstep=substeps)
        if filtered:
            mujoco.mj_kinematics(m, d)  # the tissue state and info read the tip where the step left it
        if grasp.held:
            grasp.snap_needle(d)
            grasp.hold_jaw_on_needle(d)
        return DriveResult(v_nominal=v_nominal, v_command=v_command, tip_trace=trace)

    def _held_tip(self, jaw_pos: np.ndarray, jaw_rot: np.ndarray) -> np.ndarray:
        """(3,) m the held needle's tip, world, from the jaw-tip pose."""
        grasp = self._grasp
        return jaw_pos + jaw_rot @ (grasp.position + grasp.rotation @ self._tip_local)

    def _actuate(self, point, v_point, angular, jaw_pos, jaw_rot, in_tissue: bool, tip_first: bool) -> None:
        """Joint velocity commands that move ``point`` with the twist (plain or tip-first IK, see
        ``psm.PSM``), and the tissue's resistance to the motion they make."""
        d = self._data
        if tip_first:
            qdot, jac_linear, jac_angular = self._arm.tip_first_velocity_ik(d, point, v_point, angular)
            # The tissue resists the motion the joints are asked for (part of the rotation may be dropped).
            v_point, angular = jac_linear @ qdot, jac_angular @ qdot
        else:
            qdot, jac_linear, jac_angular = self._arm.velocity_ik(d, point, v_point, angular)
        d.ctrl[self._arm.ctrl] = qdot
        d.qfrc_applied[:] = 0.0
        if self._grasp.held and in_tissue:
            centre = jaw_pos + jaw_rot @ self._grasp.position
            axis = jaw_rot @ self._grasp.rotation[:, 2]
            d.qfrc_applied[self._arm.dofs] = tissue.resistance_joint_forces(
                centre, axis, point, v_point, angular, jac_linear, jac_angular
            )
