"""The tests' policy builders (``tests/policy_builders.py``: untrained policies, dataset statistics, random
observations) for the benchmarks that time a policy without training one. The builders stay with the tests,
out of the installed plugin; this puts their folder on ``sys.path``. Not a benchmark itself."""

import sys
from pathlib import Path

sys.path.append(str(Path(__file__).resolve().parents[1] / "tests"))

from policy_builders import (  # noqa: E402
    NEEDLE_KEYPOINTS_DIM,
    SUTURE_INPUT_FEATURES,
    SUTURE_OUTPUT_FEATURES,
    fake_dataset_stats,
    random_observation,
    save_untrained_expert_policy,
    save_untrained_policy,
    tiny_config,
)

__all__ = [
    "NEEDLE_KEYPOINTS_DIM",
    "SUTURE_INPUT_FEATURES",
    "SUTURE_OUTPUT_FEATURES",
    "fake_dataset_stats",
    "random_observation",
    "save_untrained_expert_policy",
    "save_untrained_policy",
    "tiny_config",
]
