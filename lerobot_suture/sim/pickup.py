"""Needle pickup in numbers: where the needle lies on the phantom at the start, and when a pickup is done.

The needle lies flat on the tissue pad, its plane normal pointing into the tissue, so that a jaw coming
from above holds it with its z axis along the needle's normal, as every grasp of
``geometry.grasp_transform`` has it. Its centre and its turn about the surface normal are drawn per
episode (``self.np_random``) within the ranges below, in the phantom frame (origin at the pad's top
centre, z the surface normal, x the entry -> exit direction). It is a free body resting on the pad under
gravity until a closing jaw catches it (``needle_capture``).

A pickup succeeds when the jaw holds the needle with a grasp inside the ranges ``insertion`` is tested in
(``task.GRASP_RANGES["narrow"]`` about the nominal grasp: arc angle within 4 degrees of 165 degrees, within
0.5 mm along the jaw, roll within 0.05 rad), the right way round, and has lifted all of it
:data:`LIFT_HEIGHT` clear of the tissue: a throw can follow.
"""

from __future__ import annotations

import math

import numpy as np

from lerobot_suture.sim.geometry import rotation_about_x, rotation_about_z
from lerobot_suture.sim.task import GRASP_ANGLE, GRASP_RANGES

REST_CENTRE = np.array([0.0, -0.004])
"""Nominal centre of the resting needle on the pad (phantom frame x, y; m)."""
REST_RANGE_XY = 0.003
"""Half-range of the resting needle's centre about :data:`REST_CENTRE` along x and y (m)."""
REST_YAW = -math.radians(75.0)
"""Nominal turn of the resting needle about the surface normal (rad): the jaw then reaches the grasp
point with its x axis roughly along the phantom's x."""
REST_YAW_RANGE = 0.3
"""Half-range of the resting needle's turn about :data:`REST_YAW` (rad)."""
LIFT_HEIGHT = 0.005
"""Clearance of the needle's lowest point above the tissue surface that ends a pickup (m)."""


def resting_needle_pose(
    rng: np.random.Generator,
    phantom_position: np.ndarray,
    phantom_rotation: np.ndarray,
    wire_radius: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Draw where the needle lies: (centre (3,) m, rotation (3, 3)), world. Three uniform draws from
    ``rng``: centre x, centre y, turn. The wire's axis lies ``wire_radius`` (m) above the surface."""
    offset = rng.uniform(-REST_RANGE_XY, REST_RANGE_XY, size=2)
    yaw = REST_YAW + rng.uniform(-1.0, 1.0) * REST_YAW_RANGE
    local = np.array([*(REST_CENTRE + offset), wire_radius])
    # Flat, normal into the tissue: the needle frame flipped about x, then turned about the normal.
    rotation_local = rotation_about_z(yaw) @ rotation_about_x(math.pi)
    return phantom_position + phantom_rotation @ local, phantom_rotation @ rotation_local


def grasp_ready_for_throw(parameters: tuple[float, float, float], reversed_grasp: bool) -> bool:
    """Whether a grasp (arc angle rad, depth along the jaw m, roll rad) lies in the ranges an insertion is
    tested in, the right way round."""
    angle_range, offset_range, roll_range = GRASP_RANGES["narrow"]
    angle, depth, roll = parameters
    return (
        not reversed_grasp
        and abs(angle - GRASP_ANGLE) <= angle_range
        and abs(depth) <= offset_range
        and abs(roll) <= roll_range
    )


def clearance(arc_world: np.ndarray, phantom_position: np.ndarray, phantom_rotation: np.ndarray) -> float:
    """Height of the lowest of the needle's arc points (n, 3), world (m), above the tissue surface (m)."""
    heights = (arc_world - phantom_position) @ phantom_rotation[:, 2]
    return float(heights.min())
