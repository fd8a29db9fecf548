"""Speed of the CBF: microseconds per single (3,) call and states per second vectorized.

Prints one JSON object. Target: <= 20 us per single call, >= 1,000,000 states/s vectorized,
judged on the best of ``--repeats`` runs (the median is reported too).

    .venv/bin/python benchmarks/cbf_speed.py [--repeats 7]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
import timeit

import numpy as np

from lerobot_suture.safety.cbf import ellipsoid_h, filter_velocity, filter_velocity_discrete
from lerobot_suture.safety.cbf_config import CBFConfig

BAR_SINGLE_US = 20.0
BAR_STATES_PER_S = 1_000_000.0
DT = 0.1


def _rotation(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    yaw = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return yaw @ tilt


def single_call_us(fn, repeats: int, number: int = 20_000) -> dict[str, float]:
    """Mean time per call (us) in each of ``repeats`` runs: the best run (timeit's advice: the others
    measure other load on the machine) and the median run."""
    fn()
    runs = [run / number * 1e6 for run in timeit.repeat(fn, number=number, repeat=repeats)]
    return {"best": round(min(runs), 2), "median": round(statistics.median(runs), 2)}


def states_per_s(fn, batch: int, repeats: int) -> dict[str, float]:
    """States per second over ``repeats`` calls: the best call and the median call."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return {"best": round(batch / min(times)), "median": round(batch / statistics.median(times))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=9)
    args = parser.parse_args()

    config = CBFConfig()
    axes, alpha, margin = config.semi_axes, config.alpha, config.margin
    center = np.array([0.01, -0.02, 0.03])
    rotation = _rotation(0.4)
    x = center + np.array([0.004, 0.002, -0.003])
    v = np.array([0.01, 0.03, -0.005])

    single = {
        # Reference: one tiny numpy ufunc call, to read the others against on a loaded machine.
        "reference_np_add_3": single_call_us(lambda: np.add(x, v), args.repeats),
        "ellipsoid_h": single_call_us(lambda: ellipsoid_h(x, center, axes, rotation), args.repeats),
        "filter_velocity": single_call_us(lambda: filter_velocity(x, v, center, axes, alpha), args.repeats),
        "filter_velocity_rotated": single_call_us(
            lambda: filter_velocity(x, v, center, axes, alpha, rotation), args.repeats
        ),
        "filter_velocity_discrete": single_call_us(
            lambda: filter_velocity_discrete(x, v, center, axes, alpha, DT, margin), args.repeats
        ),
        "filter_velocity_discrete_rotated": single_call_us(
            lambda: filter_velocity_discrete(x, v, center, axes, alpha, DT, margin, rotation), args.repeats
        ),
    }

    rng = np.random.default_rng(0)
    vectorized = {}
    for batch in (100_000, 1_000_000):
        xs = center + rng.uniform(-1.0, 1.0, (batch, 3)) * axes  # inside and outside
        vs = rng.normal(scale=0.05, size=(batch, 3))
        vectorized[str(batch)] = {
            "filter_velocity_rotated": states_per_s(
                lambda xs=xs, vs=vs: filter_velocity(xs, vs, center, axes, alpha, rotation),
                batch,
                args.repeats,
            ),
            "filter_velocity_discrete_rotated": states_per_s(
                lambda xs=xs, vs=vs: filter_velocity_discrete(
                    xs, vs, center, axes, alpha, DT, margin, rotation
                ),
                batch,
                args.repeats,
            ),
        }

    worst_single = max(row["best"] for name, row in single.items() if not name.startswith("reference"))
    worst_rate = min(rate["best"] for row in vectorized.values() for rate in row.values())
    report = {
        "machine": {
            "cpu_count": os.cpu_count(),
            "load_average_1min": round(os.getloadavg()[0], 2),
            "python": platform.python_version(),
            "numpy": np.__version__,
        },
        "single_call_us": single,
        "vectorized_states_per_s": vectorized,
        "bar": {
            "single_call_us_max": BAR_SINGLE_US,
            "states_per_s_min": BAR_STATES_PER_S,
            "worst_single_call_us": worst_single,
            "worst_states_per_s": worst_rate,
            "pass": worst_single <= BAR_SINGLE_US and worst_rate >= BAR_STATES_PER_S,
        },
    }
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
