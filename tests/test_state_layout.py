"""The registered environment state's layout: each combination of marks, subtask and planned regrasp has a size
of its own, in the env's order, and the marks are found in any of them."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from lerobot_suture.registration import make_suture_env
from lerobot_suture.sim.state_layout import (
    LAYOUTS,
    PRIVILEGED_STATE_DIM,
    STATE_PARTS,
    part_slices,
    registered_marks,
    registered_parts,
    state_parts,
    state_size,
)
from lerobot_suture.sim.wound_marks import MARKS_DIM


def test_every_combination_has_a_size_of_its_own_and_none_is_the_privileged_one():
    combinations = [c for n in range(1, 4) for c in itertools.combinations(STATE_PARTS, n)]
    assert sorted(LAYOUTS.values()) == sorted(combinations)
    assert all(state_parts(state_size(c)) == c for c in combinations)
    assert state_parts(0) == () and state_parts(PRIVILEGED_STATE_DIM) is None and state_parts(7) is None


@pytest.mark.parametrize(
    "flags", [("marks", "regrasp_target"), ("subtask", "regrasp_target"), tuple(STATE_PARTS)]
)
def test_the_env_stacks_the_parts_where_the_layout_says(flags):
    """Each part the env stacks, alone and in a combination, lies at the layout's slice."""
    kwargs = dict(task="extraction", obs_type="pixels_agent_pos", image_size=32)
    alone = {}
    for name in flags:
        env = make_suture_env(**kwargs, **{name: True})
        obs, _ = env.reset(seed=4)
        alone[name] = obs["environment_state"]
        env.close()
    env = make_suture_env(**kwargs, **dict.fromkeys(flags, True))
    obs, _ = env.reset(seed=4)
    env.close()
    assert state_parts(obs["environment_state"].shape[-1]) == flags
    for name, where in part_slices(flags).items():
        np.testing.assert_array_equal(obs["environment_state"][where], alone[name][-STATE_PARTS[name] :])
    assert registered_parts(obs["environment_state"]).keys() == set(flags)
    marks = registered_marks(obs["environment_state"])
    if "marks" in flags:
        np.testing.assert_array_equal(marks, alone["marks"])
    else:
        assert marks is None


def test_registered_marks_reads_batches_and_refuses_the_privileged_state():
    batch = np.arange(2 * 15, dtype=np.float32).reshape(2, 15)  # marks, then the planned regrasp
    np.testing.assert_array_equal(registered_marks(batch), batch[:, :MARKS_DIM])
    assert registered_marks(np.zeros(PRIVILEGED_STATE_DIM)) is None
    assert registered_parts(np.zeros(PRIVILEGED_STATE_DIM)) is None and registered_parts(None) == {}
    assert registered_marks(None) is None
