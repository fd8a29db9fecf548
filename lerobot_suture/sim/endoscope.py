"""The endoscope: its viewpoint about the work site, its images, and where world points fall in them."""

from __future__ import annotations

import math

import mujoco
import numpy as np

from lerobot_suture.sim.geometry import project_to_image, quat_from_matrix
from lerobot_suture.sim.rendering import make_renderer, update_poses, upload_texture

# Viewpoint of the training data: spherical about the work site (rad, m).
ENDOSCOPE_TARGET = np.array([0.0, 0.0, 0.012])
ENDOSCOPE_AZIMUTH = math.radians(90.0)
ENDOSCOPE_ELEVATION = math.radians(52.0)
ENDOSCOPE_DISTANCE = 0.105


class Endoscope:
    """The scene's ``endoscope`` camera (looked up once) and its two renderers, made on first use.

    Args:
        model: The scene's MuJoCo model; the viewpoint is written into its camera.
        image_size: Side (px) of the observation images.
        render_size: Side (px) of the ``render()`` frames (videos).
    """

    def __init__(self, model: mujoco.MjModel, image_size: int, render_size: int):
        self._model = model
        self._camera = model.camera("endoscope").id
        self._image_size = image_size
        self._render_size = render_size
        self._renderer = None
        self._video_renderer = None
        self._jitter_offset = np.zeros(3)
        self._jitter_roll = 0.0
        self._viewpoint = (0.0, 0.0)

    @property
    def viewpoint(self) -> tuple[float, float]:
        """(azimuth, elevation) offsets (rad) of the current viewpoint from the training view."""
        return self._viewpoint

    def set_jitter(self, position_offset: np.ndarray = (0.0, 0.0, 0.0), roll: float = 0.0) -> None:
        """Hold the camera ``position_offset`` (3,) m from, and rolled ``roll`` rad about its optical axis
        relative to, every viewpoint :meth:`set_viewpoint` places it at (appearance randomization); the
        jitter stays through a scenario's change of viewpoint. Call :meth:`set_viewpoint` to apply it."""
        self._jitter_offset = np.asarray(position_offset, dtype=np.float64).copy()
        self._jitter_roll = float(roll)

    def set_viewpoint(self, azimuth_offset: float = 0.0, elevation_offset: float = 0.0) -> None:
        """Place the camera on its sphere about the work site, offset from the training view (rad)."""
        self._viewpoint = (float(azimuth_offset), float(elevation_offset))
        az = ENDOSCOPE_AZIMUTH + azimuth_offset
        el = ENDOSCOPE_ELEVATION + elevation_offset
        pos = ENDOSCOPE_TARGET + ENDOSCOPE_DISTANCE * np.array(
            [math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]
        )
        forward = ENDOSCOPE_TARGET - pos
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, forward)
        if self._jitter_roll or self._jitter_offset.any():
            # Rolling the camera by +roll turns the image by -roll.
            c, s = math.cos(self._jitter_roll), math.sin(self._jitter_roll)
            right, up = c * right + s * up, c * up - s * right
            pos = pos + self._jitter_offset
        self._model.cam_pos[self._camera] = pos
        self._model.cam_quat[self._camera] = quat_from_matrix(np.column_stack([right, up, -forward]))

    def update_poses(self, data: mujoco.MjData) -> None:
        """Bring body and camera poses up to date before a render or a projection."""
        update_poses(self._model, data)

    def image(self, data: mujoco.MjData) -> np.ndarray:
        """The observation image, (image_size, image_size, 3) uint8."""
        if self._renderer is None:
            self._renderer = make_renderer(self._model, self._image_size, self._image_size)
        self.update_poses(data)
        self._renderer.update_scene(data, camera=self._camera)
        return self._renderer.render().copy()

    def video_frame(self, data: mujoco.MjData) -> np.ndarray:
        """A ``render()`` frame, (render_size, render_size, 3) uint8."""
        if self._video_renderer is None:
            self._video_renderer = make_renderer(self._model, self._render_size, self._render_size)
        self.update_poses(data)
        self._video_renderer.update_scene(data, camera=self._camera)
        return self._video_renderer.render()

    def project(self, data: mujoco.MjData, points: np.ndarray) -> np.ndarray:
        """Where world points (n, 3) m fall in the image: (2 n,) float32 ``[x, y]`` per point in [-1, 1]
        (x right, y down; ``geometry.project_to_image``). Call :meth:`update_poses` first."""
        camera_rotation = data.cam_xmat[self._camera].reshape(3, 3)
        fovy = math.radians(float(self._model.cam_fovy[self._camera]))
        return (
            project_to_image(points, data.cam_xpos[self._camera], camera_rotation, fovy)
            .ravel()
            .astype(np.float32)
        )

    def upload_texture(self, texture_id: int) -> None:
        """Send a texture whose pixels changed in the model to the renderers made so far (renderers made
        later upload every texture when they open)."""
        upload_texture(self._model, (self._renderer, self._video_renderer), texture_id)

    def close(self) -> None:
        for r in (self._renderer, self._video_renderer):
            if r is not None:
                r.close()
        self._renderer = self._video_renderer = None
