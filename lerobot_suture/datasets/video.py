"""Pick the video decoding backend that works on this machine.

LeRobot decodes dataset videos with ``torchcodec`` when it loads and with ``pyav`` otherwise
(``lerobot.utils.import_utils.get_safe_default_video_backend``). ``torchcodec`` needs a system
FFmpeg of a matching major version; where it is missing, ``import torchcodec`` raises and LeRobot logs a
long traceback each time it falls back. Asking once, quietly, and passing the answer as
``video_backend=`` (or ``--dataset.video_backend=`` to ``lerobot-train``) gives the same choice
without the noise.
"""

from __future__ import annotations

import functools
import importlib

VIDEO_BACKENDS = ("torchcodec", "pyav")
# Each backend and the module it decodes with, in order of preference.
BACKEND_MODULES = {"torchcodec": "torchcodec", "pyav": "av"}


@functools.cache
def _loads(module: str) -> bool:
    try:
        importlib.import_module(module)
    except (ImportError, OSError, RuntimeError):
        return False
    return True


def first_loading_backend(backend_modules: dict[str, str]) -> str:
    """The first backend of ``backend_modules`` (backend -> module, in order of preference) whose module
    imports here.

    Raises:
        RuntimeError: if none does.
    """
    for backend, module in backend_modules.items():
        if _loads(module):
            return backend
    raise RuntimeError(
        f"No video decoder loads here (tried modules {list(backend_modules.values())}): torchcodec needs a "
        "system FFmpeg (e.g. `apt-get install ffmpeg`) and pyav is not installed (`pip install av`). Or record "
        "without video: --video=false."
    )


def resolve_video_backend(preferred: str | None = None) -> str:
    """The backend to decode videos with: ``preferred`` if given, else torchcodec if it loads, else pyav.

    Args:
        preferred: ``"torchcodec"``, ``"pyav"`` or None (detect).

    Raises:
        ValueError: if ``preferred`` is not a known backend.
        RuntimeError: if no backend loads.
    """
    if preferred is not None:
        if preferred not in VIDEO_BACKENDS:
            raise ValueError(f"`video_backend` must be one of {VIDEO_BACKENDS} or None. Got {preferred!r}.")
        return preferred
    return first_loading_backend(BACKEND_MODULES)
