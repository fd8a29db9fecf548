"""The rule that turns a closing jaw into a held needle, and the grasp it makes. Pure numpy.

The jaw's geoms do not push the needle (they have no contacts); whether a closing jaw catches the needle is
decided here, once, at the control step in which its closure command reaches 0.5 while it is still open
wider than the wire (``grasp.NeedleGrasp.try_capture``). It catches the needle when the wire crosses the
jaw's centre plane (x = 0 in the jaw-tip frame, the plane between the jaw's side edges):

- within the jaw's length: from :data:`JAW_GRIP_LENGTH` behind the jaw tip to a wire radius beyond it
  (``-JAW_GRIP_LENGTH <= z <= wire radius``);
- within :data:`CAPTURE_HALF_GAP` of the faces' mid-plane (``|y|``): the closing faces sweep it in;
- with the wire's tangent within :data:`CAPTURE_MAX_TILT` of the jaw's x axis (across the jaw).

The closed faces seat the wire: the crossing point moves onto the jaw's axis (x = y = 0) at the depth it
crossed, and the needle turns about it so that the wire runs straight across the jaw (along +x or -x), the
smallest turn that does it. So a grasp moves the needle by at most ``CAPTURE_HALF_GAP`` and turns it by
at most ``CAPTURE_MAX_TILT``.

Frames as in ``geometry.grasp_transform``: needle pose in the jaw-tip frame (position (3,) m, rotation
(3, 3)); the needle's arc runs from the tip (arc angle 0) to the tail (pi) in its own xy-plane.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lerobot_suture.sim.geometry import NEEDLE_ARC, NEEDLE_RADIUS, cross3

JAW_GRIP_LENGTH = 0.006
"""How far behind the jaw tip the faces can hold the wire (m); the faces are 7 mm long."""
CAPTURE_HALF_GAP = 0.001
"""How far from the faces' mid-plane a closing jaw still catches the wire (m)."""
CAPTURE_MAX_TILT = math.radians(30.0)
"""Largest angle between the wire and the jaw's x axis that the closing faces straighten (rad)."""


@dataclass(frozen=True)
class SeatedGrasp:
    """A needle seated in the closed jaw.

    Attributes:
        position: (3,) the needle's centre in the jaw-tip frame (m).
        rotation: (3, 3) the needle frame in the jaw-tip frame.
        arc_angle: where along the arc the jaw holds it (rad; 0 the tip, pi the tail).
        depth: the wire's position along the jaw axis from the jaw tip (m; negative inside the jaw), the
            ``offset_along_jaw`` of ``geometry.grasp_transform``.
        roll: the needle plane's tilt about the jaw's x axis from the jaw's z axis (rad, in (-pi, pi]).
        reversed: the arc runs along -x: the needle sits the other way round from the grasps
            ``geometry.grasp_transform`` describes (no throw starts from it).
    """

    position: np.ndarray
    rotation: np.ndarray
    arc_angle: float
    depth: float
    roll: float
    reversed: bool

    @property
    def parameters(self) -> tuple[float, float, float]:
        """(arc angle rad, depth m, roll rad), the parameters of ``geometry.grasp_transform``."""
        return self.arc_angle, self.depth, self.roll


def wire_crossings(position: np.ndarray, rotation: np.ndarray, radius: float = NEEDLE_RADIUS) -> list[float]:
    """Arc angles (rad, in [0, NEEDLE_ARC]) at which the needle's wire crosses the jaw's plane x = 0."""
    a, b = radius * rotation[0, 0], radius * rotation[0, 1]
    amplitude = math.hypot(a, b)
    if amplitude < 1e-12:
        return []
    c = -float(position[0]) / amplitude
    if abs(c) > 1.0:
        return []
    phase, spread = math.atan2(b, a), math.acos(c)
    angles = []
    for phi in (phase + spread, phase - spread):
        phi = math.remainder(phi, 2.0 * math.pi)
        if phi < 0:
            phi += 2.0 * math.pi
        if 0.0 <= phi <= NEEDLE_ARC and all(abs(phi - other) > 1e-9 for other in angles):
            angles.append(phi)
    return angles


def seat_needle(
    position: np.ndarray,
    rotation: np.ndarray,
    wire_radius: float,
    radius: float = NEEDLE_RADIUS,
) -> SeatedGrasp | None:
    """The grasp a closing jaw makes of a needle at ``position``, ``rotation`` (jaw-tip frame), or None
    when the rule (module docstring) says the jaw misses it.

    Args:
        position: (3,) needle centre in the jaw-tip frame (m).
        rotation: (3, 3) needle frame in the jaw-tip frame.
        wire_radius: the needle wire's radius (m).
        radius: the needle's radius (m).
    """
    position = np.asarray(position, dtype=np.float64)
    rotation = np.asarray(rotation, dtype=np.float64)
    best: tuple[float, float, np.ndarray, np.ndarray] | None = None
    for phi in wire_crossings(position, rotation, radius):
        c, s = math.cos(phi), math.sin(phi)
        point = position + rotation @ np.array([radius * c, radius * s, 0.0])
        tangent = rotation @ np.array([-s, c, 0.0])
        if abs(point[1]) > CAPTURE_HALF_GAP or not -JAW_GRIP_LENGTH <= point[2] <= wire_radius:
            continue
        if abs(tangent[0]) < math.cos(CAPTURE_MAX_TILT):
            continue
        if best is None or abs(point[1]) < abs(best[1][1]):
            best = (phi, point, tangent, rotation[:, 2])
    if best is None:
        return None
    phi, point, tangent, normal = best
    along = 1.0 if tangent[0] > 0 else -1.0
    seated_tangent = np.array([along, 0.0, 0.0])
    seated_normal = normal - (normal @ seated_tangent) * seated_tangent
    seated_normal /= np.linalg.norm(seated_normal)
    radial = cross3(seated_tangent, seated_normal)  # centre -> wire, since normal = radial x tangent
    c, s = math.cos(phi), math.sin(phi)
    x_axis = c * radial - s * seated_tangent
    y_axis = s * radial + c * seated_tangent
    seated_rotation = np.column_stack([x_axis, y_axis, seated_normal])
    depth = float(point[2])
    seated_position = np.array([0.0, 0.0, depth]) - radius * radial
    roll = math.atan2(-seated_normal[1], seated_normal[2])
    return SeatedGrasp(seated_position, seated_rotation, phi, depth, roll, along < 0)
