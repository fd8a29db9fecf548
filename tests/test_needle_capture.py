"""The capture rule: a closing jaw catches the needle only where the rule says, and seats it by a bounded move."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from lerobot_suture.sim.geometry import NEEDLE_RADIUS, grasp_transform, matrix_from_rotvec
from lerobot_suture.sim.needle_capture import (
    CAPTURE_HALF_GAP,
    CAPTURE_MAX_TILT,
    JAW_GRIP_LENGTH,
    seat_needle,
    wire_crossings,
)

WIRE_RADIUS = 0.0004


def _arc_point(position, rotation, phi):
    return position + rotation @ np.array([NEEDLE_RADIUS * math.cos(phi), NEEDLE_RADIUS * math.sin(phi), 0.0])


@given(
    angle=st.floats(0.05, math.pi - 0.05),
    depth=st.floats(-JAW_GRIP_LENGTH + 1e-4, 0.0),
    roll=st.floats(-0.5, 0.5),
)
@settings(max_examples=200, deadline=None)
def test_a_needle_already_seated_stays_where_it_is(angle, depth, roll):
    position, rotation = grasp_transform(angle, 0.0, roll)
    position = position + np.array([0.0, 0.0, depth])  # the wire on the jaw axis at this depth
    seated = seat_needle(position, rotation, WIRE_RADIUS)
    assert seated is not None and not seated.reversed
    np.testing.assert_allclose(seated.rotation, rotation, atol=1e-9)
    np.testing.assert_allclose(seated.position, position, atol=1e-9)
    assert abs(seated.arc_angle - angle) < 1e-9
    assert abs(seated.depth - depth) < 1e-12 and abs(seated.roll - roll) < 1e-9


@given(
    position=st.lists(st.floats(-0.015, 0.015), min_size=3, max_size=3),
    rotvec=st.lists(st.floats(-math.pi, math.pi), min_size=3, max_size=3),
)
@settings(max_examples=500, deadline=None)
def test_any_capture_obeys_the_rule_and_moves_the_needle_a_bounded_amount(position, rotvec):
    position, rotation = np.array(position), matrix_from_rotvec(np.array(rotvec))
    seated = seat_needle(position, rotation, WIRE_RADIUS)
    if seated is None:
        return
    phi = seated.arc_angle
    before = _arc_point(position, rotation, phi)
    after = _arc_point(seated.position, seated.rotation, phi)
    # The caught point was between the faces, within the jaw, and ends on the jaw axis at its depth.
    assert abs(before[0]) < 1e-9 and abs(before[1]) <= CAPTURE_HALF_GAP + 1e-12
    assert -JAW_GRIP_LENGTH - 1e-12 <= before[2] <= WIRE_RADIUS + 1e-12
    np.testing.assert_allclose(after, [0.0, 0.0, before[2]], atol=1e-12)
    # The wire runs across the jaw, and the needle turned by at most the tilt the faces straighten.
    tangent = seated.rotation @ np.array([-math.sin(phi), math.cos(phi), 0.0])
    np.testing.assert_allclose(np.abs(tangent), [1.0, 0.0, 0.0], atol=1e-9)
    turn = math.acos(np.clip((np.trace(rotation.T @ seated.rotation) - 1) / 2, -1, 1))
    assert turn <= CAPTURE_MAX_TILT + 1e-9
    np.testing.assert_allclose(seated.rotation.T @ seated.rotation, np.eye(3), atol=1e-9)


def test_the_jaw_misses_a_needle_outside_its_faces_beyond_its_tip_or_along_it():
    position, rotation = grasp_transform(math.radians(165), 0.0, 0.0)
    assert seat_needle(position, rotation, WIRE_RADIUS) is not None
    for shift in ([0.0, 2 * CAPTURE_HALF_GAP, 0.0], [0.0, 0.0, 0.002], [0.0, 0.0, -JAW_GRIP_LENGTH - 0.001]):
        assert seat_needle(position + np.array(shift), rotation, WIRE_RADIUS) is None, shift
    # A wire 60 degrees off the jaw's x axis (more than the faces straighten) is not caught.
    along = matrix_from_rotvec(np.array([0.0, 0.0, math.radians(60)]))
    assert seat_needle(along @ position, along @ rotation, WIRE_RADIUS) is None


def test_a_needle_caught_the_other_way_round_is_marked_reversed():
    position, rotation = grasp_transform(math.radians(165), 0.0, 0.0)
    flip = matrix_from_rotvec(np.array([0.0, 0.0, math.pi]))  # the jaw turned half a turn about its axis
    seated = seat_needle(flip @ position, flip @ rotation, WIRE_RADIUS)
    assert seated is not None and seated.reversed


def test_wire_crossings_lie_on_the_arc_and_in_the_plane():
    rng = np.random.default_rng(0)
    for _ in range(200):
        position = rng.uniform(-0.012, 0.012, 3)
        rotation = matrix_from_rotvec(rng.uniform(-math.pi, math.pi, 3))
        for phi in wire_crossings(position, rotation):
            assert 0.0 <= phi <= math.pi
            assert abs(_arc_point(position, rotation, phi)[0]) < 1e-12
