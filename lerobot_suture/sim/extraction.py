"""Needle extraction in numbers: the finished throw an episode starts from, and when an extraction is done.

An episode starts where an insertion ends: the needle through the tissue from the entry point to the exit
point, its tip protruding an arc of :data:`PROTRUSION_RANGE` beyond the exit point (drawn per episode),
held at its tail with the episode's grasp. Released, the needle stays lodged in the tissue, which holds it
(``grasp.NeedleGrasp.rest``). The task: let go, regrasp the needle near its tip, and pull it out along its
arc, so that the tail follows the tip out through the exit hole.

One instrument arm does it, as a surgeon's needle driver does: the instrument's roll and the wrist turn the
jaw about the needle's axis through the half turn the pull takes (a second arm would be needed to hand the
needle back to a grasp at its tail for the next throw, not to extract it).

Success: the jaw holds the needle, all of it is out of the tissue, its tail left through the exit hole
(within :data:`TAIL_EXIT_TOLERANCE` of the exit point), and the tissue strain of the episode (the needle's
accumulated off-arc motion in tissue, ``tissue``) stayed within :data:`STRAIN_BOUND`.
"""

from __future__ import annotations

import math

import numpy as np

from lerobot_suture.sim.geometry import (
    grasp_transform,
    insertion_frame,
    jaw_holding,
    matrix_from_rotvec,
    step_towards,
)
from lerobot_suture.sim.task import EXIT_TOLERANCE, NEEDLE_TILT

PROTRUSION_RANGE = (0.5, 0.7)
"""Arc (rad) of the needle beyond the exit point at the start: 5 to 7 mm of a 10 mm radius needle."""
REGRASP_ANGLE = 0.25
"""Arc angle from the tip (rad) at which the scripted expert regrasps the needle: 2.5 mm from the tip."""
TAIL_EXIT_TOLERANCE = EXIT_TOLERANCE
"""How far from the exit point the tail may leave the tissue (m)."""
STRAIN_BOUND = 0.002
"""Largest accumulated off-arc motion of the needle in tissue over an extraction (m)."""
BACK_OFF = 0.006
"""How far a regrasping jaw draws back along its axis from the wire before and after a grasp (m)."""
PULL_MARGIN = 0.3
"""How far past the exit point a pull drives the needle's tail (rad of arc)."""
SWEEP_STEPS = 24
"""Poses along the finished throw that set up the start's insertion record (entry and exit crossings)."""


def start_drive_angle(rng: np.random.Generator, exit_angle: float) -> float:
    """The needle's drive angle (rad, about its centre from the entry pose) at the start: one draw."""
    low, high = PROTRUSION_RANGE
    return exit_angle + float(rng.uniform(low, high))


def throw_sweep(start_angle: float) -> np.ndarray:
    """Drive angles (rad) from just before the tip meets the entry point to ``start_angle``: the throw the
    start state records as done."""
    return np.linspace(-0.1, start_angle, SWEEP_STEPS)


def extraction_succeeded(held: bool, extracted: bool, tail_exit_error: float, strain: float) -> bool:
    """Whether an extraction is done (module docstring); lengths in m."""
    return held and extracted and tail_exit_error <= TAIL_EXIT_TOLERANCE and strain <= STRAIN_BOUND


def planned_regrasp(
    entry_point: np.ndarray, exit_point: np.ndarray, surface_normal: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The jaw pose (position (3,) m, rotation (3, 3), world) that grasps the needle of a throw planned through
    the marks ``entry_point`` and ``exit_point`` (m) on a surface of unit normal ``surface_normal``.

    What a system with the registered wound and the needle's geometry knows: the needle of a throw on its
    marks lies on the planned arc, its tip an unknown arc in :data:`PROTRUSION_RANGE` past the exit point.
    The plan takes the middle of that range and grasps :data:`REGRASP_ANGLE` short of that tip, so the grasp
    lands on the wire whatever the protrusion, up to half the range (about 1 mm) along it.
    """
    frame = insertion_frame(entry_point, exit_point, surface_normal, NEEDLE_TILT)
    drive = frame.exit_angle + 0.5 * sum(PROTRUSION_RANGE)
    return jaw_holding(frame.centre, frame.needle_rotation(drive), *grasp_transform(REGRASP_ANGLE, 0.0, 0.0))


def turn_left(jaw_rot: np.ndarray, goal_rot: np.ndarray) -> float:
    """How far (rad, in [0, 2 pi)) the jaw of rotation ``jaw_rot`` (3, 3) must still turn about its own axis, in
    the positive sense (against the pull's), to reach the heading of ``goal_rot`` (3, 3)."""
    x_goal = jaw_rot.T @ goal_rot[:, 0]
    angle = math.atan2(x_goal[1], x_goal[0]) % (2.0 * math.pi)
    return 0.0 if angle > 2.0 * math.pi - 1e-3 else angle


def reach_step(
    jaw_pos: np.ndarray,
    jaw_rot: np.ndarray,
    short: np.ndarray,
    grasp_rot: np.ndarray,
    left: float,
    max_distance: float,
    max_turn: float,
) -> tuple[np.ndarray, np.ndarray]:
    """One bounded step (position (3,) m, rotation (3, 3)) of a regrasp's reach from the jaw at ``jaw_pos``,
    ``jaw_rot`` towards ``short`` (m) and the grasp's heading ``grasp_rot``, ``left`` (:func:`turn_left`) still to
    turn. While more than a quarter turn is left, the jaw turns about its own axis in the sense that leaves the
    pull the instrument's roll; the last quarter turn (the shortest way now) aligns every axis."""
    if math.pi / 2 < left < 2.0 * math.pi - 0.5:
        position, _ = step_towards(jaw_pos, jaw_rot, short, jaw_rot, max_distance, 0.0)
        return position, matrix_from_rotvec(max_turn * jaw_rot[:, 2]) @ jaw_rot
    return step_towards(jaw_pos, jaw_rot, short, grasp_rot, max_distance, max_turn)
