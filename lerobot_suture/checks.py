"""Checks that configs share, so one kind of bad value gets one message whichever config holds it."""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable


def check_positive(config: object, names: Iterable[str], unit: str = "") -> None:
    """Refuse the first field of ``names`` on ``config`` that is not a finite number > 0.

    Args:
        config: the dataclass being validated (its ``__post_init__`` calls this).
        names: the fields to check.
        unit: the fields' unit (``"m"``, ``"rad/s"``), named in the message when given.

    Raises:
        ValueError: naming the field, the bound and the value given.
    """
    for name in names:
        value = getattr(config, name)
        if (
            isinstance(value, bool)
            or not isinstance(value, numbers.Real)
            or not (math.isfinite(value) and value > 0)
        ):
            unit_note = f" ({unit})" if unit else ""
            raise ValueError(f"`{name}` must be a finite number > 0{unit_note}. Got {value!r}.")


def check_count(config: object, name: str, minimum: int) -> None:
    """Refuse the field ``name`` on ``config`` unless it is an integer >= ``minimum``.

    Raises:
        ValueError: naming the field, the bound and the value given.
    """
    value = getattr(config, name)
    if not isinstance(value, int) or value < minimum:
        raise ValueError(f"`{name}` must be an integer >= {minimum}. Got {value!r}.")


def check_jaw_thresholds(closed_above: float, holding_below: float) -> None:
    """Refuse jaw thresholds (closure, 0 open, 1 closed) that are not 0 < ``closed_above`` < ``holding_below`` <= 1.

    Raises:
        ValueError: naming both values.
    """
    if not 0.0 < closed_above < holding_below <= 1.0:
        raise ValueError(
            "The jaw thresholds must satisfy 0 < closed_above < holding_below <= 1. Got "
            f"closed_above={closed_above}, holding_below={holding_below}."
        )
