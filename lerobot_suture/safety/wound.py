"""What a real system registers about a throw: the wound (entry and exit points, tissue normal) and where the
needle sits in the jaw (the grasp model). Validated at construction. Units: m, rad.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lerobot_suture.safety.cbf import ellipsoid_h, suture_ellipsoid_frame
from lerobot_suture.safety.surface_cbf import surface_height
from lerobot_suture.sim.geometry import NEEDLE_RADIUS, grasp_transform, needle_arc_points
from lerobot_suture.sim.task import GRASP_ANGLE

_ARC_POINTS = 16


def finite_vector(name: str, value, size: int) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64).reshape(-1)
    if v.shape != (size,) or not np.all(np.isfinite(v)):
        raise ValueError(f"`{name}` must be {size} finite numbers. Got {np.asarray(value).tolist()!r}.")
    return v


@dataclass(frozen=True)
class Wound:
    """A registered wound: where the throw enters and leaves the tissue (world, m).

    Args:
        entry_point: (3,) the marked entry point on the tissue surface.
        exit_point: (3,) the marked exit point; apart from the entry along the surface.
        surface_normal: (3,) the tissue surface normal, out of the tissue (any length > 0).
        throw_index: which throw of a running suture it is (a new index starts a new throw).
    """

    entry_point: np.ndarray
    exit_point: np.ndarray
    surface_normal: np.ndarray
    throw_index: int = 0

    def __post_init__(self):
        entry = finite_vector("entry_point", self.entry_point, 3)
        exit_ = finite_vector("exit_point", self.exit_point, 3)
        normal = finite_vector("surface_normal", self.surface_normal, 3)
        if np.linalg.norm(normal) < 1e-9:
            raise ValueError(
                "`surface_normal` must be a non-zero vector (the tissue normal, out of the tissue)."
            )
        object.__setattr__(self, "entry_point", entry)
        object.__setattr__(self, "exit_point", exit_)
        object.__setattr__(self, "surface_normal", normal / np.linalg.norm(normal))
        # Computed once (it raises when entry and exit are not apart on the surface): the guard and the
        # env wrapper read it several times per control step.
        object.__setattr__(self, "_frame", suture_ellipsoid_frame(entry, exit_, normal))

    def ellipsoid_frame(self) -> tuple[np.ndarray, np.ndarray]:
        """(centre (3,) m, world-from-ellipsoid rotation (3, 3)) of the throw's ellipsoid."""
        return self._frame

    def barrier(self, points: np.ndarray, semi_axes: np.ndarray) -> np.ndarray:
        """The safe set's barrier at ``points`` (..., 3) m for an ellipsoid of ``semi_axes`` (3,) m: the larger of
        the ellipsoid's h and the height above the tissue surface in units of the normal semi-axis. >= 0
        exactly where the tip may be (above the tissue, or in the ellipsoid); (...,) float64."""
        center, rotation = self._frame
        h = np.asarray(ellipsoid_h(points, center, semi_axes, rotation))
        height = surface_height(points, self.entry_point, self.surface_normal) / semi_axes[2]
        return np.maximum(h, height)


@dataclass
class GraspModel:
    """Where the needle sits in the jaw (the grasp model; ``geometry.grasp_transform``), draccus-compatible.

    Args:
        angle: arc angle of the grasp point (rad), in (0, pi).
        offset_along_jaw: shift of the needle along the jaw axis (m), |offset| <= 5 mm.
        roll: tilt of the needle about the jaw's x axis (rad), |roll| <= 0.5.
        radius: needle radius (m), > 0.
    """

    angle: float = GRASP_ANGLE
    offset_along_jaw: float = 0.0
    roll: float = 0.0
    radius: float = NEEDLE_RADIUS

    def __post_init__(self):
        checks = {
            "angle": (0.0, np.pi, self.angle),
            "offset_along_jaw": (-0.005, 0.005, self.offset_along_jaw),
            "roll": (-0.5, 0.5, self.roll),
            "radius": (1e-4, 0.1, self.radius),
        }
        for name, (low, high, value) in checks.items():
            if isinstance(value, bool) or not isinstance(value, int | float) or not low <= value <= high:
                raise ValueError(f"`{name}` must be a number in [{low}, {high:.4g}]. Got {value!r}.")

    def needle_in_jaw(self) -> tuple[np.ndarray, np.ndarray]:
        """(position (3,) m, rotation (3, 3)) of the needle frame in the jaw-tip frame."""
        return grasp_transform(self.angle, self.offset_along_jaw, self.roll, self.radius)

    def arc_in_jaw(self, n_points: int = _ARC_POINTS) -> np.ndarray:
        """(n, 3) m points along the needle in the jaw-tip frame, tip first."""
        position, rotation = self.needle_in_jaw()
        return position + needle_arc_points(n_points, self.radius) @ rotation.T

    def tip_in_jaw(self) -> np.ndarray:
        """(3,) m the needle tip in the jaw-tip frame."""
        return self.arc_in_jaw(2)[0]
