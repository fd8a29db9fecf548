"""The patient-side manipulator (PSM) in the scene: its six arm joints looked up once, the jaw-tip pose,
and the joint velocities that move a point of the instrument (the needle tip while it is held).

The arithmetic is ``controller``'s pure functions; this module reads MuJoCo's Jacobians for them. The
env writes the joint velocities into ``data.ctrl``. Units: m, rad, s.
"""

from __future__ import annotations

import mujoco
import numpy as np

from lerobot_suture.sim import controller
from lerobot_suture.sim.task import CONTROL_DT

ARM_JOINTS = ("outer_yaw", "outer_pitch", "insertion", "instrument_roll", "wrist_pitch", "wrist_yaw")
"""The arm's joints (and their velocity actuators) in ``assets/scene.xml``, base to wrist."""

# Controller: reach the target pose in one control step, within these speeds.
TIME_TO_TARGET = CONTROL_DT
MAX_LINEAR_SPEED = 0.05  # m/s
MAX_ANGULAR_SPEED = 2.0  # rad/s
IK_DAMPING = 0.01
IK_LINEAR_WEIGHT = 10.0  # 0.1 m of tip motion weighs as much as 1 rad of turn
IK_UPDATES_WHEN_FILTERED = 10  # IK solves per control step (100 Hz) while a tip-velocity filter acts
SEGMENT_TRACKING_GAIN = 20.0  # 1/s: feedback on the tip's distance from its filtered segment, per IK solve
JOINT_LIMIT_LOOKAHEAD = 0.03  # s: a joint covers at most its distance to a range stop in this time


class PSM:
    """The arm's joints, actuators and jaw-tip frame in a MuJoCo model, and its inverse kinematics.

    Args:
        model: The scene's MuJoCo model.

    Attributes:
        dofs: (6,) dof addresses of the arm joints.
        qpos: (6,) qpos addresses of the arm joints.
        ctrl: (6,) actuator ids of the arm's velocity actuators.
        ctrl_limit: (6,) joint speed limits of those actuators (rad/s; m/s for insertion).
        joint_range: (2, 6) low and high range stops of the arm joints.
        jaw_body: Id of the ``jaw`` body (the Jacobians are taken on it).
        jaw_site: Id of the ``jaw_tip`` site (the frame the action commands).
    """

    def __init__(self, model: mujoco.MjModel):
        m = model
        self._model = model
        self.dofs = np.array([m.joint(n).dofadr[0] for n in ARM_JOINTS])
        self.qpos = np.array([m.joint(n).qposadr[0] for n in ARM_JOINTS])
        self.ctrl_limit = np.array([m.actuator(n).ctrlrange[1] for n in ARM_JOINTS])
        self.joint_range = m.jnt_range[[m.joint(n).id for n in ARM_JOINTS]].T.copy()  # (2, 6) low, high
        self.ctrl = np.array([m.actuator(n).id for n in ARM_JOINTS])
        self.jaw_body = m.body("jaw").id
        self.jaw_site = m.site("jaw_tip").id

    def jaw_pose(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """Jaw-tip pose, world: (position (3,) m, rotation (3, 3)), as of MuJoCo's last kinematics."""
        return data.site_xpos[self.jaw_site].copy(), data.site_xmat[self.jaw_site].reshape(3, 3).copy()

    def solve_jaw_pose(
        self, data: mujoco.MjData, target_pos: np.ndarray, target_rot: np.ndarray
    ) -> np.ndarray:
        """Arm joints (6,) that put the jaw tip at a target pose: kinematic IK from ``data``'s joints.

        Moves ``data.qpos`` of the arm (200 damped steps, inside the range stops) and returns it.
        """
        m, d = self._model, data
        jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        lo, hi = self.joint_range
        for _ in range(200):
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)  # the Jacobian needs the dof frames
            p, r = self.jaw_pose(d)
            lin, ang = controller.pose_velocity_command(p, r, target_pos, target_rot, 1.0, 1.0, 1.0)
            mujoco.mj_jac(m, d, jacp, jacr, p, self.jaw_body)
            jac = np.vstack([IK_LINEAR_WEIGHT * jacp[:, self.dofs], jacr[:, self.dofs]])
            qdot = controller.damped_least_squares(
                jac, np.concatenate([IK_LINEAR_WEIGHT * lin, ang]), IK_DAMPING
            )
            d.qpos[self.qpos] = np.clip(d.qpos[self.qpos] + 0.5 * qdot, lo, hi)
        return d.qpos[self.qpos].copy()

    def _jacobians(self, data: mujoco.MjData, point: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Linear and angular Jacobians (3, 6) of the arm joints at ``point`` (3,) on the jaw body."""
        m = self._model
        jacp = np.zeros((3, m.nv))
        jacr = np.zeros((3, m.nv))
        mujoco.mj_jac(m, data, jacp, jacr, point, self.jaw_body)
        return jacp[:, self.dofs], jacr[:, self.dofs]

    def velocity_ik(
        self, data: mujoco.MjData, point: np.ndarray, v_point: np.ndarray, angular: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Joint velocities for the twist (``v_point`` (3,) m/s at ``point``, ``angular`` (3,) rad/s):
        damped differential IK on both together, scaled uniformly into the actuators' speed limits so
        the direction of motion survives.

        Returns:
            (qdot (6,), linear Jacobian (3, 6), angular Jacobian (3, 6)) at ``point``.
        """
        jac_linear, jac_angular = self._jacobians(data, point)
        jacobian = np.vstack([IK_LINEAR_WEIGHT * jac_linear, jac_angular])
        twist = np.concatenate([IK_LINEAR_WEIGHT * v_point, angular])
        qdot = controller.damped_least_squares(jacobian, twist, IK_DAMPING)
        scale = float(np.max(np.abs(qdot) / self.ctrl_limit))
        if scale > 1.0:
            qdot /= scale
        return qdot, jac_linear, jac_angular

    def tip_first_velocity_ik(
        self, data: mujoco.MjData, point: np.ndarray, v_point: np.ndarray, angular: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Joint velocities by tip-first IK at ``point`` (``controller.tip_first_velocity_ik``): the
        linear velocity first, inside the joints' speed and range bounds, the rotation in its null space.

        Returns:
            (qdot (6,), linear Jacobian (3, 6), angular Jacobian (3, 6)) at ``point``.
        """
        jac_linear, jac_angular = self._jacobians(data, point)
        low, high = controller.joint_velocity_bounds(
            data.qpos[self.qpos], *self.joint_range, self.ctrl_limit, JOINT_LIMIT_LOOKAHEAD
        )
        qdot, _, _ = controller.tip_first_velocity_ik(
            jac_linear, jac_angular, v_point, angular, low, high, IK_DAMPING / IK_LINEAR_WEIGHT, IK_DAMPING
        )
        return qdot, jac_linear, jac_angular
