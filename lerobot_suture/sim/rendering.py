"""Headless rendering: pick a MuJoCo GL backend that works, and say what to do when none does."""

from __future__ import annotations

import os
import sys

_FIX = (
    "Install an OpenGL backend for headless rendering (Debian/Ubuntu: `apt-get install libegl1 "
    "libgl1-mesa-dri` for EGL, or `libosmesa6` for OSMesa) and set MUJOCO_GL=egl (or osmesa); on a "
    "desktop with a display, MUJOCO_GL=glfw."
)


_state = {"imported_too_early": False}


def select_gl_backend() -> str:
    """Set ``MUJOCO_GL`` before MuJoCo is imported, when the user has not chosen one.

    Linux without a display gets EGL (Mesa's llvmpipe renders on the CPU); elsewhere MuJoCo's own
    default (GLFW) is kept. Returns the backend in force.
    """
    backend = os.environ.get("MUJOCO_GL")
    if backend:
        return backend
    if "mujoco" in sys.modules:
        # MuJoCo picks its GL backend when first imported; too late to choose for it.
        _state["imported_too_early"] = True
    if sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
        os.environ["MUJOCO_GL"] = "egl"
        # PyOpenGL must agree with MuJoCo on the platform.
        os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
        return "egl"
    return "glfw"


def make_renderer(model, height: int, width: int):
    """A ``mujoco.Renderer``, with an error that names the fix when no GL backend works."""
    import mujoco

    try:
        return mujoco.Renderer(model, height=height, width=width)
    except Exception as exc:  # noqa: BLE001 - any GL failure gets the same actionable message
        backend = os.environ.get("MUJOCO_GL", "<unset>")
        hint = (
            " `mujoco` was imported before `lerobot_suture`, so MuJoCo chose its GL backend before "
            "ours: set MUJOCO_GL=egl in the environment, or import lerobot_suture first."
            if _state["imported_too_early"]
            else ""
        )
        raise RuntimeError(
            f"MuJoCo could not open a rendering context (MUJOCO_GL={backend}): {exc}.{hint} {_FIX}"
        ) from exc


def upload_texture(model, renderers, texture_id: int) -> None:
    """Send a texture whose pixels changed in ``model`` to each of ``renderers`` made so far (None: not made;
    a renderer made later uploads every texture when it opens)."""
    import mujoco

    for r in renderers:
        if r is None:
            continue
        # mujoco.Renderer keeps its GL and MuJoCo render contexts private; the upload needs both.
        r._gl_context.make_current()
        mujoco.mjr_uploadTexture(model, r._mjr_context, texture_id)


def update_poses(model, data) -> None:
    """Bring body and camera poses up to date before a render or a projection: the held needle was snapped,
    and a camera may have moved, after MuJoCo's last forward pass."""
    import mujoco

    mujoco.mj_kinematics(model, data)
    mujoco.mj_camlight(model, data)
