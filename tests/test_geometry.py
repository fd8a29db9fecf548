"""Pure geometry: where a world point falls in the endoscope image; how far a wire holds a jaw open; the angle
of a rotation."""

import math

import numpy as np
import pytest

from lerobot_suture.sim.geometry import (
    jaw_angle_on_wire,
    matrix_from_rotvec,
    project_to_image,
    rotation_angle_of,
    rotvec_from_matrix,
)


def test_projection_of_points_on_the_axis_and_at_the_edge_of_the_view():
    # A camera 0.1 m above the origin looking straight down (backward axis +z), right = +x, up = +y.
    position, rotation = np.array([0.0, 0.0, 0.1]), np.eye(3)
    fovy = math.radians(40.0)
    half = 0.1 * math.tan(fovy / 2)  # half the view's height on the plane z = 0
    points = np.array([[0.0, 0.0, 0.0], [0.0, half, 0.0], [half / 2, -half, 0.0], [0.0, half, -0.1]])
    np.testing.assert_allclose(
        project_to_image(points, position, rotation, fovy),
        [[0.0, 0.0], [0.0, -1.0], [0.5, 1.0], [0.0, -0.5]],  # y down; twice as far, half the offset
        atol=1e-12,
    )


def test_points_behind_the_camera_are_an_error():
    with pytest.raises(ValueError, match="behind the camera"):
        project_to_image(np.array([[0.0, 0.0, 0.2]]), np.array([0.0, 0.0, 0.1]), np.eye(3), 1.0)


def test_jaw_angle_on_wire():
    # A 0.8 mm wire in jaws whose faces close to 0.2 mm, 8 mm from the hinge: atan(0.6 / 8).
    assert jaw_angle_on_wire(0.0008, 0.0002, 0.008) == pytest.approx(math.atan(0.075))
    assert jaw_angle_on_wire(0.0008, 0.0002, 0.0075) > jaw_angle_on_wire(0.0008, 0.0002, 0.0085)
    assert jaw_angle_on_wire(0.0001, 0.0002, 0.008) == 0.0  # thinner than the gap
    with pytest.raises(ValueError, match="`distance_from_pivot` must be > 0 m"):
        jaw_angle_on_wire(0.0008, 0.0002, 0.0)


def test_rotation_angle_of_recovers_the_angle_of_any_axis_angle_rotation():
    rng = np.random.default_rng(0)
    # Random axes at angles spread over [0, pi], the two ends included, where rounding pushes the
    # trace past its range.
    angles = np.concatenate([[0.0, 1e-9, math.pi - 1e-9, math.pi], rng.uniform(0.0, math.pi, 200)])
    for angle in angles:
        axis = rng.normal(size=3)
        rotation = matrix_from_rotvec(angle * axis / np.linalg.norm(axis))
        assert rotation_angle_of(rotation) == pytest.approx(angle, abs=1e-6)
        assert np.linalg.norm(rotvec_from_matrix(rotation)) == pytest.approx(angle, abs=1e-6)
        # The angle between two rotations is that of the one taking the first to the second.
        base = matrix_from_rotvec(rng.normal(size=3))
        assert rotation_angle_of(base.T @ (base @ rotation)) == pytest.approx(angle, abs=1e-6)
