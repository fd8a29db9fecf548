"""A camera on the instrument's shaft, looking down it at the jaw and the tissue beyond, as SutureBot and
SRT-H mount one on each instrument. Opt-in (``SutureEnv(wrist_camera=True)``): an env without it compiles
the scene as it always did, so its episodes are unchanged.

The camera rides on the ``instrument`` body: it follows the port's yaw and pitch, the insertion and the
instrument's roll, not the wrist's pitch and yaw, so the jaw moves in its image as the wrist turns.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from lerobot_suture.sim.rendering import make_renderer, update_poses, upload_texture

WRIST_CAMERA = "wrist"
WRIST_CAMERA_POS = (0.005, 0.0, 0.03)
"""The camera in the instrument's frame (m): 5 mm off the shaft's axis, 30 mm above the wrist."""
WRIST_CAMERA_TILT = math.radians(10.0)
"""Its tilt (rad) from the shaft's direction towards the axis, so the jaw sits near the image's centre."""
WRIST_CAMERA_FOVY = 70.0
"""Its vertical field of view (degrees)."""


def add_wrist_camera(spec: mujoco.MjSpec) -> None:
    """Add the wrist camera to the instrument of a scene spec (before it is compiled)."""
    camera = spec.body("instrument").add_camera()
    camera.name = WRIST_CAMERA
    camera.pos = WRIST_CAMERA_POS
    # A MuJoCo camera looks along its -z; turning it about y by the tilt points it down the shaft (the
    # instrument's -z) and towards the axis (-x).
    camera.quat = [math.cos(WRIST_CAMERA_TILT / 2), 0.0, math.sin(WRIST_CAMERA_TILT / 2), 0.0]
    camera.fovy = WRIST_CAMERA_FOVY


class WristCamera:
    """The scene's wrist camera and its renderer, made on first use.

    Args:
        model: a model compiled from a spec with :func:`add_wrist_camera`.
        image_size: side (px) of its images.
    """

    def __init__(self, model: mujoco.MjModel, image_size: int):
        self._model = model
        self._camera = model.camera(WRIST_CAMERA).id
        self._image_size = image_size
        self._renderer = None

    def image(self, data: mujoco.MjData) -> np.ndarray:
        """The wrist image, (image_size, image_size, 3) uint8."""
        if self._renderer is None:
            self._renderer = make_renderer(self._model, self._image_size, self._image_size)
        update_poses(self._model, data)
        self._renderer.update_scene(data, camera=self._camera)
        return self._renderer.render().copy()

    def upload_texture(self, texture_id: int) -> None:
        """Send a texture whose pixels changed in the model to the renderer, if made."""
        upload_texture(self._model, (self._renderer,), texture_id)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
        self._renderer = None
