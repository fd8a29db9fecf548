"""The needle in the instrument's jaw: a kinematic grasp, the jaw reading it leaves, its loss and its capture.

While held, the needle moves rigidly with the jaw tip, at a pose in the jaw frame (drawn per episode, or made
by the jaw closing on it), and the wire stops the closing jaw a little open, so the jaw reading shows whether
it holds the needle, as a real needle driver's does. Released, the needle is a free body under gravity. A
jaw that closes on a free needle catches it by the rule of ``needle_capture``.

A needle lodged in the tissue is caught only as it lies: a jaw whose seat would move any point of it more than
``LODGED_CAPTURE_TOLERANCE`` closes beside it (the tissue holds it), where a free needle would be snapped into
the seat; the snap of a lodged needle would twist it through the tissue in an instant. Nor does a seat push a
needle into the tissue: a jaw whose seat would put any point of the needle more than that tolerance deeper in
the tissue pad than the needle lies closes beside it too (the tissue's surface holds a needle lying on it).

A free needle lying still on the phantom, or lodged in its tissue, rests (:meth:`NeedleGrasp.rest`): static
friction or the tissue holds it and nothing else touches it (the jaw has no contacts), so it is held in
place kinematically, weightless and without contacts, which spares the contact solver every physics step;
the phantom carries it when it moves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from lerobot_suture.sim.geometry import (
    cross3,
    grasp_transform,
    jaw_angle_on_wire,
    needle_arc_points,
    needle_in_world,
    quat_from_matrix,
)
from lerobot_suture.sim.needle_capture import SeatedGrasp, seat_needle
from lerobot_suture.sim.psm import PSM
from lerobot_suture.sim.task import GRASP_ANGLE

LODGED_CAPTURE_TOLERANCE = 0.0005
"""How far (m) a jaw's seat may move any point of a needle lodged in tissue for the jaw to catch it (a regrasp
aligned with the needle moves it about 0.01 mm)."""
JAW_OPEN_ANGLE = 0.6
"""The jaw joint's range (rad): a closure command of 0 opens it this far."""
_LODGED_CHECK_POINTS = 7
_NEEDLE_CONTACT_BIT = 2  # the needle geoms' contype in scene.xml


@dataclass(frozen=True)
class CaptureVerdict:
    """What a closing jaw does with the free needle (:meth:`NeedleGrasp.capture_verdict`).

    Attributes:
        seated: the grasp it makes, or None when it misses.
        rule: ``caught``; or the rule that lets the needle go: ``not_between_faces`` (``needle_capture``),
            ``jaw_too_closed`` (the wire cannot pass between the faces), ``lodged`` (the seat would move a
            needle lodged in tissue more than ``LODGED_CAPTURE_TOLERANCE``), ``into_pad`` (it would push the
            needle into the tissue pad).
        shift: the largest move (m) the seat would make of any point of the needle (nan without a seat).
    """

    seated: SeatedGrasp | None
    rule: str
    shift: float = math.nan


class NeedleGrasp:
    """The grasp between the jaw and the needle of one compiled scene (``assets/scene.xml``).

    Attributes:
        held: Whether the jaw holds the needle.
        position, rotation: The needle's pose in the jaw-tip frame ((3,) m, (3, 3)).
        parameters: (arc angle rad, offset along the jaw m, roll rad) the pose was made from, or that
            describe the grasp the jaw made (``needle_capture.SeatedGrasp``).
        reversed: The jaw caught the needle the other way round from any grasp a throw starts from.
        resting: The free needle lies still on the phantom or is lodged in it, held there kinematically
            (:meth:`rest`).
        captures: How many times the jaw has caught the needle this episode.
    """

    def __init__(self, model: mujoco.MjModel, arm: PSM):
        m = model
        self._model = m
        self._arm = arm
        self.jaw_ctrl = m.actuator("jaw").id
        self.jaw_qpos = m.joint("jaw").qposadr[0]
        self._jaw_dof = m.joint("jaw").dofadr[0]
        self._jaw_pivot_to_tip = float(m.site("jaw_tip").pos[2])
        # Inner faces of the closed jaws are this far apart (m): the jaw geoms' offsets less their half-thickness.
        self._jaw_closed_gap = float(
            m.geom("jaw_upper").pos[1]
            - m.geom("jaw_lower").pos[1]
            - m.geom_size[m.geom("jaw_upper").id][1] * 2
        )
        self.needle_body = m.body("needle").id
        self._needle_qpos = m.joint("needle").qposadr[0]
        self._needle_dof = m.joint("needle").dofadr[0]
        needle_geom = int(np.flatnonzero(m.geom_bodyid == self.needle_body)[0])
        self._wire_diameter = 2.0 * float(m.geom_size[needle_geom][0])
        self._pad_geom = m.geom("tissue_pad").id
        self.reset()

    def set(self, angle: float, offset_along_jaw: float, roll: float) -> None:
        """Hold the needle at arc angle ``angle`` (rad), ``offset_along_jaw`` (m) and ``roll`` (rad); see
        :func:`geometry.grasp_transform`. Moves nothing: :meth:`snap_needle` puts the needle there."""
        self.parameters = (float(angle), float(offset_along_jaw), float(roll))
        self.position, self.rotation = grasp_transform(angle, offset_along_jaw, roll)

    @property
    def offset_along_jaw(self) -> float:
        """Where along the jaw the wire sits, from the nominal grasp point (m)."""
        return self.parameters[1]

    def needle_pose(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """Needle centre and orientation, world: (position (3,) m, rotation (3, 3))."""
        if self.held:
            return needle_in_world(*self._arm.jaw_pose(data), self.position, self.rotation)
        return data.xpos[self.needle_body].copy(), data.xmat[self.needle_body].reshape(3, 3).copy()

    def held_jaw_angle(self) -> float:
        """Jaw opening (rad) while it holds the needle: the wire keeps the jaws apart."""
        return jaw_angle_on_wire(
            self._wire_diameter, self._jaw_closed_gap, self._jaw_pivot_to_tip + self.offset_along_jaw
        )

    @property
    def closure_command(self) -> float:
        """The last closure command (:meth:`command_jaw`), in [0, 1]."""
        return self._last_closure

    def command_jaw(self, data: mujoco.MjData, closure: float, in_tissue: bool) -> None:
        """The jaw's position command for ``closure`` in [0, 1] (1 closed); below 0.5 the needle is let go,
        and a command that rises to 0.5 or more closes the jaw on the needle if it catches it
        (:meth:`try_capture`)."""
        closing = closure >= 0.5 and self._last_closure < 0.5
        self._last_closure = closure
        if closure < 0.5 and self.held:
            self.release(data, in_tissue)
        elif closing and not self.held:
            self.try_capture(data, in_tissue)
        target = (1.0 - closure) * JAW_OPEN_ANGLE
        data.ctrl[self.jaw_ctrl] = max(target, self.held_jaw_angle()) if self.held else target

    def jaw_closure(self, data: mujoco.MjData) -> float:
        """The jaw reading as a closure: 1 closed, 0 fully open."""
        return 1.0 - float(data.qpos[self.jaw_qpos]) / JAW_OPEN_ANGLE

    def hold_jaw_on_needle(self, data: mujoco.MjData) -> None:
        """The needle stops the closing jaw at the wire (an opening command still opens it)."""
        held = self.held_jaw_angle()
        if data.qpos[self.jaw_qpos] < held:
            data.qpos[self.jaw_qpos] = held
            data.qvel[self._jaw_dof] = 0.0

    def capture_verdict(self, data: mujoco.MjData, in_tissue: bool = False) -> CaptureVerdict:
        """What a jaw closing now would do with the free needle (nothing changes): the seat it would make, or
        which rule of :meth:`try_capture` lets the needle go."""
        jaw_pos, jaw_rot = self._arm.jaw_pose(data)
        centre = data.xpos[self.needle_body]
        rotation = data.xmat[self.needle_body].reshape(3, 3)
        seated = seat_needle(jaw_rot.T @ (centre - jaw_pos), jaw_rot.T @ rotation, 0.5 * self._wire_diameter)
        if seated is None:
            return CaptureVerdict(None, "not_between_faces")
        wire_angle = jaw_angle_on_wire(
            self._wire_diameter, self._jaw_closed_gap, self._jaw_pivot_to_tip + seated.depth
        )
        if data.qpos[self.jaw_qpos] <= wire_angle:
            return CaptureVerdict(None, "jaw_too_closed")  # the wire cannot pass between its faces
        arc = needle_arc_points(_LODGED_CHECK_POINTS)  # (n, 3) in the needle frame
        seated_arc = jaw_pos + (seated.position + arc @ seated.rotation.T) @ jaw_rot.T
        lying_arc = centre + arc @ rotation.T
        shift = float(np.max(np.linalg.norm(seated_arc - lying_arc, axis=1)))
        if in_tissue and shift > LODGED_CAPTURE_TOLERANCE:  # the tissue holds it: the jaw closes beside it
            return CaptureVerdict(None, "lodged", shift)
        if self._pad_depth(data, seated_arc) > self._pad_depth(data, lying_arc) + LODGED_CAPTURE_TOLERANCE:
            return CaptureVerdict(None, "into_pad", shift)  # the tissue's surface holds the needle
        return CaptureVerdict(seated, "caught", shift)

    def try_capture(self, data: mujoco.MjData, in_tissue: bool = False) -> bool:
        """Close the jaw on the free needle: held from now on, seated as ``needle_capture.seat_needle``
        says, if the wire lies between the faces of a jaw open wider than the wire there, and, for a needle
        lodged in tissue (``in_tissue``), if the seat moves it by at most ``LODGED_CAPTURE_TOLERANCE``.
        Returns whether it caught the needle."""
        if self.held:
            return False
        seated = self.capture_verdict(data, in_tissue).seated
        if seated is None:
            return False
        self.parameters = seated.parameters
        self.position, self.rotation = seated.position, seated.rotation
        self.reversed = seated.reversed
        self.held = True
        self.resting = False
        self.captures += 1
        self._model.body_gravcomp[self.needle_body] = 1.0
        self.set_pad_collides_with_needle(False)
        self.snap_needle(data)
        return True

    def snap_needle(self, data: mujoco.MjData) -> None:
        """The held needle moves rigidly with the jaw: put its free body where the grasp says."""
        self._set_needle_free_pose(data, *self.needle_pose(data))
        data.qvel[self._needle_dof : self._needle_dof + 6] = 0.0

    def release(self, data: mujoco.MjData, in_tissue: bool) -> None:
        """The jaw loses the needle. In tissue, the tissue holds it: it stays lodged where it is, resting
        (:meth:`rest`). Otherwise it keeps its current velocity and falls under gravity."""
        if not self.held:
            return
        centre, rot = self.needle_pose(data)
        self._set_needle_free_pose(data, centre, rot)
        if in_tissue:
            self.held = False
            self.rest(data)
            return
        # Carry the jaw's velocity into the needle's free joint.
        vel = np.zeros(6)
        jaw_body = self._arm.jaw_body
        mujoco.mj_objectVelocity(self._model, data, mujoco.mjtObj.mjOBJ_BODY, jaw_body, vel, 0)
        data.qvel[self._needle_dof : self._needle_dof + 3] = vel[3:] + cross3(
            vel[:3], centre - data.xpos[jaw_body]
        )
        data.qvel[self._needle_dof + 3 : self._needle_dof + 6] = rot.T @ vel[:3]
        self._model.body_gravcomp[self.needle_body] = 0.0
        self.set_pad_collides_with_needle(True)  # a needle lost above the phantom lands on it
        self.held = False
        self.resting = False

    def reset(self, held: bool = True) -> None:
        """Start an episode with the nominal grasp parameters. Held (``held``): weightless while held, and
        passing through the pad (the insertion model owns the tissue's effect on a held needle), the jaw
        closed. Free: under gravity, resting on the pad, the jaw open."""
        self.held = bool(held)
        self.resting = False
        self.reversed = False
        self.captures = 0
        self._last_closure = 1.0 if held else 0.0
        self.set(GRASP_ANGLE, 0.0, 0.0)
        self._model.body_gravcomp[self.needle_body] = 1.0 if held else 0.0
        self.set_pad_collides_with_needle(not held)

    def set_pad_collides_with_needle(self, collides: bool) -> None:
        bit = _NEEDLE_CONTACT_BIT if collides else 0
        self._model.geom_conaffinity[self._pad_geom] = bit
        # MuJoCo's broad phase filters on the per-body union of the geoms' bits too.
        self._model.body_conaffinity[self._model.geom_bodyid[self._pad_geom]] = bit

    @property
    def wire_diameter(self) -> float:
        """The needle wire's diameter (m)."""
        return self._wire_diameter

    def place_free_needle(self, data: mujoco.MjData, centre: np.ndarray, rotation: np.ndarray) -> None:
        """Put the free (not held) needle at ``centre`` (3,) m, ``rotation`` (3, 3), world, resting there."""
        if self.held:
            raise RuntimeError("the jaw holds the needle; release it before placing it.")
        self._set_needle_free_pose(data, centre, rotation)
        self.rest(data)

    def rest(self, data: mujoco.MjData) -> None:
        """Hold the free needle still where it lies: weightless, no contacts, no velocity."""
        data.qvel[self._needle_dof : self._needle_dof + 6] = 0.0
        self._model.body_gravcomp[self.needle_body] = 1.0
        self.set_pad_collides_with_needle(False)
        self.resting = True

    def needle_speed(self, data: mujoco.MjData) -> float:
        """Speed of the free needle's centre (m/s)."""
        return float(np.linalg.norm(data.qvel[self._needle_dof : self._needle_dof + 3]))

    def _pad_depth(self, data: mujoco.MjData, points: np.ndarray) -> float:
        """How deep (m, >= 0) the deepest of ``points`` (n, 3) world lies in the tissue pad (0 if none is in it)."""
        half = self._model.geom_size[self._pad_geom]
        local = (points - data.geom_xpos[self._pad_geom]) @ data.geom_xmat[self._pad_geom].reshape(3, 3)
        inside = np.all(np.abs(local) <= half, axis=1)
        return float(np.max(half[2] - local[inside, 2], initial=0.0))

    def _set_needle_free_pose(self, data: mujoco.MjData, centre: np.ndarray, rotation: np.ndarray) -> None:
        q = self._needle_qpos
        data.qpos[q : q + 3] = centre
        data.qpos[q + 3 : q + 7] = quat_from_matrix(rotation)
