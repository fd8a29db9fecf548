"""Saving figures small: every plot the package writes goes through :func:`save_figure`.

A matplotlib plot saved as 8-bit palette PNG is about a third of its true-colour size and looks the same (a
plot has few colours), which keeps ``docs/results`` within its size budget. Imports nothing of the package, so
every floor may use it (``tests/test_layout.py`` lets each).
"""

from __future__ import annotations

import io
from pathlib import Path


def save_figure(
    fig, path: str | Path, dpi: float | None = None, palette: bool = True, **savefig_kwargs
) -> Path:
    """Write matplotlib ``fig`` to ``path`` as a 256-colour PNG (parents created); returns the path.

    ``dpi`` and ``savefig_kwargs`` go to ``Figure.savefig`` (``dpi`` None: the figure's own). ``palette``
    False keeps true colour, for figures of camera images, which 256 colours would band.
    """
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi or "figure", **savefig_kwargs)
    if not palette:
        path.write_bytes(buffer.getvalue())
        return path
    buffer.seek(0)
    with Image.open(buffer) as image:
        quantized = image.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT)
    quantized.save(path, format="PNG", optimize=True)
    return path
