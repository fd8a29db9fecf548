"""Rigid-body geometry for the suturing task: poses, the 10-dim pose vector, and the needle's arc.

Pure numpy functions; no MuJoCo. Positions in metres, angles in radians, rotations as 3x3
matrices (world-from-body) unless a name says otherwise.

The 10-dim pose vector used for both action and ``agent_pos`` (the paper's representation) is
``[x, y, z, r11, r21, r31, r12, r22, r32, jaw]``: the position, the first two *columns* of the
rotation matrix, and the jaw closure in [0, 1] (1 = fully closed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

POSE_DIM = 10
NEEDLE_RADIUS = 0.010
"""Radius of the semicircular suture needle (m), as in ``assets/scene.xml``."""
NEEDLE_ARC = math.pi
"""Angular length of the needle (rad): a semicircle, tip at angle 0, tail at angle pi."""


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two 3-vectors; ~20x faster than ``np.cross`` at this size (hot path)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def rot6_from_matrix(rotation: np.ndarray) -> np.ndarray:
    """First two columns of a rotation matrix, (3, 3) -> (6,)."""
    return np.concatenate([rotation[:, 0], rotation[:, 1]])


def matrix_from_rot6(rot6: np.ndarray) -> np.ndarray:
    """Rotation matrix from two (possibly non-orthonormal) columns by Gram-Schmidt, (6,) -> (3, 3).

    Raises:
        ValueError: if the two columns are degenerate (zero or parallel).
    """
    a = np.asarray(rot6[:3], dtype=np.float64)
    b = np.asarray(rot6[3:6], dtype=np.float64)
    na = math.sqrt(a @ a)
    if na < 1e-9:
        raise ValueError("the first rotation column of the pose is zero; it must be a unit vector.")
    x = a / na
    b = b - (x @ b) * x
    nb = math.sqrt(b @ b)
    if nb < 1e-9:
        raise ValueError("the two rotation columns of the pose are parallel; they must be orthogonal.")
    y = b / nb
    return np.column_stack([x, y, cross3(x, y)])


def pose_vector(position: np.ndarray, rotation: np.ndarray, jaw: float) -> np.ndarray:
    """Pack a pose into the 10-dim vector, float64."""
    out = np.empty(POSE_DIM)
    out[:3] = position
    out[3:9] = rot6_from_matrix(rotation)
    out[9] = jaw
    return out


def rotation_angle_of(rotation: np.ndarray) -> float:
    """Angle (rad, in [0, pi]) of a rotation matrix; of ``a.T @ b`` for the angle between ``a`` and ``b``."""
    cos = (float(rotation[0, 0] + rotation[1, 1] + rotation[2, 2]) - 1.0) * 0.5
    # Rounding can push the trace of a near-identity or near-half-turn rotation past +-1.
    return math.acos(min(1.0, max(-1.0, cos)))


def rotvec_from_matrix(rotation: np.ndarray) -> np.ndarray:
    """Axis-angle vector (rad) of a rotation matrix; robust near 0 and pi."""
    angle = rotation_angle_of(rotation)
    skew = np.array(
        [
            rotation[2, 1] - rotation[1, 2],
            rotation[0, 2] - rotation[2, 0],
            rotation[1, 0] - rotation[0, 1],
        ]
    )
    if angle < 1e-6:
        return 0.5 * skew
    if math.pi - angle < 1e-4:
        # Near pi the skew part vanishes; take the axis from the symmetric part.
        sym = (rotation + np.eye(3)) * 0.5
        axis = sym[:, int(np.argmax(np.diag(sym)))]
        axis = axis / np.linalg.norm(axis)
        return axis * angle
    return skew * (angle / (2.0 * math.sin(angle)))


def matrix_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of an axis-angle vector (Rodrigues)."""
    angle = math.sqrt(float(rotvec @ rotvec))
    if angle < 1e-12:
        return np.eye(3)
    k = rotvec / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * kx + (1.0 - math.cos(angle)) * (kx @ kx)


def segment_distance(points: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Distance (m) from each of ``points`` (..., 3) to the segment ``start`` -> ``end`` ((3,) each, m)."""
    points = np.asarray(points, dtype=np.float64)
    chord = end - start
    length2 = float(chord @ chord)
    if length2 == 0.0:
        return np.linalg.norm(points - start, axis=-1)
    s = np.clip((points - start) @ chord / length2, 0.0, 1.0)
    return np.linalg.norm(points - (start + s[..., None] * chord), axis=-1)


def rotation_about_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_about_x(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def quat_from_matrix(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), MuJoCo's convention, of a rotation matrix."""
    m = rotation
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def step_towards(
    position: np.ndarray,
    rotation: np.ndarray,
    goal_position: np.ndarray,
    goal_rotation: np.ndarray,
    max_distance: float,
    max_angle: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The pose one bounded step from (``position`` (3,) m, ``rotation`` (3, 3)) towards the goal: at most
    ``max_distance`` (m) of translation and ``max_angle`` (rad) of turn."""
    delta = goal_position - position
    distance = float(np.linalg.norm(delta))
    if distance > max_distance:
        delta *= max_distance / distance
    rotvec = rotvec_from_matrix(rotation.T @ goal_rotation)
    angle = float(np.linalg.norm(rotvec))
    if angle > max_angle:
        rotvec *= max_angle / angle
    return position + delta, rotation @ matrix_from_rotvec(rotvec)


def needle_arc_points(n_points: int, radius: float = NEEDLE_RADIUS) -> np.ndarray:
    """Points along the needle in its own frame, from the tip (angle 0) to the tail (pi), (n, 3)."""
    phi = np.linspace(0.0, NEEDLE_ARC, n_points)
    return np.stack([radius * np.cos(phi), radius * np.sin(phi), np.zeros_like(phi)], axis=1)


@dataclass(frozen=True)
class InsertionFrame:
    """Where the needle's centre must sit, and how it must turn, to pass entry -> exit.

    The needle's plane contains the entry-exit line and is tilted by ``tilt`` from the phantom's
    normal towards the lateral axis; the needle's centre sits above the chord so that the arc dips
    below the surface between the two points. Rotating the needle by ``-beta`` about its own z axis
    (``axis``) from ``start_rotation`` drives the tip from the entry point, under the wound, out of
    the exit point.

    Attributes:
        centre: (3,) needle centre during the throw, world (m).
        axis: (3,) needle z axis (plane normal) during the throw, world unit vector.
        start_rotation: (3, 3) needle orientation with the tip on the entry point (beta = 0).
        exit_angle: beta (rad) at which the tip reaches the exit point.
    """

    centre: np.ndarray
    axis: np.ndarray
    start_rotation: np.ndarray
    exit_angle: float

    def needle_rotation(self, beta: float) -> np.ndarray:
        """Needle orientation after driving by ``beta`` (rad) about its centre."""
        return self.start_rotation @ rotation_about_z(-beta)


def insertion_frame(
    entry_point: np.ndarray,
    exit_point: np.ndarray,
    surface_normal: np.ndarray,
    tilt: float,
    radius: float = NEEDLE_RADIUS,
) -> InsertionFrame:
    """The needle's throw geometry for an entry/exit pair (see :class:`InsertionFrame`).

    Args:
        entry_point: (3,) world (m).
        exit_point: (3,) world (m).
        surface_normal: (3,) unit normal of the tissue surface, pointing out of the tissue.
        tilt: tilt of the needle plane from the surface normal (rad), towards the lateral axis.
        radius: needle radius (m); must exceed half the entry-exit distance.
    """
    chord = exit_point - entry_point
    half = 0.5 * float(np.linalg.norm(chord))
    if not 0.0 < half < radius:
        raise ValueError(
            f"entry-exit distance {2 * half:.4f} m must be in (0, {2 * radius:.4f}) m for a needle "
            f"of radius {radius} m."
        )
    u = chord / (2.0 * half)
    normal = surface_normal - (surface_normal @ u) * u
    normal /= np.linalg.norm(normal)
    lateral = cross3(normal, u)
    axis = math.cos(tilt) * lateral - math.sin(tilt) * normal
    up = math.sin(tilt) * lateral + math.cos(tilt) * normal
    height = math.sqrt(radius**2 - half**2)
    centre = entry_point + half * u + height * up
    x_axis = (entry_point - centre) / radius
    y_axis = cross3(axis, x_axis)
    start = np.column_stack([x_axis, y_axis, axis])
    exit_angle = 2.0 * math.acos(height / radius)
    return InsertionFrame(centre=centre, axis=axis, start_rotation=start, exit_angle=exit_angle)


def needle_in_world(
    jaw_pos: np.ndarray, jaw_rot: np.ndarray, grasp_pos: np.ndarray, grasp_rot: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The needle's world pose (centre (3,) m, rotation (3, 3)) held by the jaw at ``jaw_pos``,
    ``jaw_rot`` with the grasp ``grasp_pos``, ``grasp_rot`` (the needle's pose in the jaw frame)."""
    return jaw_pos + jaw_rot @ grasp_pos, jaw_rot @ grasp_rot


def jaw_holding(
    needle_pos: np.ndarray, needle_rot: np.ndarray, grasp_pos: np.ndarray, grasp_rot: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The jaw's world pose (position (3,) m, rotation (3, 3)) that puts the needle it holds with the
    grasp ``grasp_pos``, ``grasp_rot`` at ``needle_pos``, ``needle_rot``: the inverse of
    :func:`needle_in_world`."""
    jaw_rot = needle_rot @ grasp_rot.T
    return needle_pos - jaw_rot @ grasp_pos, jaw_rot


def grasp_transform(grasp_angle: float, offset_along_jaw: float, roll: float, radius: float = NEEDLE_RADIUS):
    """Needle pose in the jaw frame for a grasp at arc angle ``grasp_angle`` (rad).

    The jaw's z axis points out of the instrument and is parallel to the needle's plane normal; the
    jaw's x axis runs along the needle's tangent at the grasp point; so the needle's centre lies at
    ``radius`` along the jaw's y axis. ``offset_along_jaw`` (m) shifts the needle along the jaw
    axis, ``roll`` (rad) tilts it about the jaw's x axis (grasp imperfections).

    Returns:
        (position (3,), rotation (3, 3)): the needle frame in the jaw frame.
    """
    c, s = math.cos(grasp_angle), math.sin(grasp_angle)
    # Jaw axes in the needle frame: tangent, towards the centre, plane normal.
    jaw_in_needle = np.array([[-s, -c, 0.0], [c, -s, 0.0], [0.0, 0.0, 1.0]])
    rotation = jaw_in_needle.T
    position = np.array([0.0, radius, offset_along_jaw])
    tilt = rotation_about_x(roll)
    return tilt @ position, tilt @ rotation


def jaw_angle_on_wire(wire_diameter: float, closed_gap: float, distance_from_pivot: float) -> float:
    """Opening (rad) of a hinged jaw closed on a wire: the wire holds the jaw faces ``wire_diameter``
    apart (m) at ``distance_from_pivot`` (m) from the hinge, where closed they would be ``closed_gap`` (m)
    apart. Zero when the wire is no thicker than the gap."""
    if distance_from_pivot <= 0:
        raise ValueError(f"`distance_from_pivot` must be > 0 m. Got {distance_from_pivot}.")
    return math.atan(max(wire_diameter - closed_gap, 0.0) / distance_from_pivot)


def project_to_image(
    points: np.ndarray, camera_position: np.ndarray, camera_rotation: np.ndarray, fovy: float
) -> np.ndarray:
    """Where world points fall in a pinhole camera's square image, in normalized coordinates.

    Args:
        points: (n, 3) world positions (m).
        camera_position: (3,) the camera's position (m).
        camera_rotation: (3, 3) world-from-camera, MuJoCo's convention: columns right, up, backward.
        fovy: the vertical field of view (rad).

    Returns:
        (n, 2) ``[x, y]`` with x to the right and y down, -1 and 1 at the image's edges (the pixel grid's
        convention, so a resize keeps them). Points behind the camera raise a ValueError.
    """
    in_camera = (np.asarray(points, dtype=np.float64) - camera_position) @ camera_rotation
    depth = -in_camera[:, 2]
    if np.any(depth <= 0):
        raise ValueError("A point lies behind the camera; it has no image position.")
    focal = 1.0 / math.tan(fovy / 2)
    return np.stack([focal * in_camera[:, 0] / depth, -focal * in_camera[:, 1] / depth], axis=1)
