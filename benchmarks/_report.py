"""How a benchmark script ends: the machine it ran on, its JSON on stdout and, with ``--output``, in a file.

Imported by the scripts beside it (``python benchmarks/NAME.py`` puts this folder on ``sys.path``); not a
benchmark itself, so ``make bench`` skips it.
"""

from __future__ import annotations

import json
import os
from pathlib import Path


def machine() -> dict:
    """The cores and the 1-minute load average: what a figure measured on a shared machine depends on."""
    return {"cpu_count": os.cpu_count(), "load_average_1min": round(os.getloadavg()[0], 2)}


def write(report: dict, output: Path) -> None:
    """Write ``report`` to ``output`` as compact JSON (its folder made): a long run's partial result, or its
    result for ``docs/results``, which keeps to a size budget."""
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(json.dumps(report, separators=(",", ":")) + "\n")


def emit(report: dict, output: Path | None) -> None:
    """Print ``report`` as indented JSON, and write it to ``output`` too when given."""
    print(json.dumps(report, indent=2))
    if output is not None:
        write(report, output)
