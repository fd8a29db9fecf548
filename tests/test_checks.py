"""The checks configs share (``lerobot_suture.checks``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from lerobot_suture.checks import check_positive


@dataclass
class _Config:
    speed: object = 0.01
    rate: object = 1


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf"), True, "0.01", None])
def test_a_field_that_is_not_a_finite_number_above_zero_is_named_with_its_unit(bad):
    with pytest.raises(ValueError, match=r"`speed` must be a finite number > 0 \(m/s\). Got"):
        check_positive(_Config(speed=bad), ("speed", "rate"), unit="m/s")


def test_finite_positive_numbers_of_any_real_type_pass():
    check_positive(_Config(speed=np.float32(0.02), rate=3), ("speed", "rate"))
