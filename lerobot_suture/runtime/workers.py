"""Rollouts in worker processes: the seeds split into batches of ``batch_envs``, each batch rolled out by one
of ``workers`` processes holding its own copy of the policy.

On a CPU the ensemble's small GEMMs gain little from a second torch thread (the U-Net's step ran 1.5x
faster on 2 threads than on 1), while two processes of one thread each run two batches at once: the work
divides by the cores. Each episode's noise comes from its own seed (:class:`PolicyRunner`), so an episode
is the same whichever process rolls it out.

The pool is kept while the same (policy, device, config overrides, workers) comes back (a worker spends
seconds importing torch and loading the policy) and the policy's directory is unchanged (a calibration written since, or
weights trained over, start fresh workers); a call for another policy replaces it (one copy of one policy per
worker at a time, whatever a program evaluates in turn), and it is shut down at exit. The envs of a worker are rebuilt only when
the env factory changes.
"""

from __future__ import annotations

import atexit
import multiprocessing
import os
import pickle
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

from tqdm import tqdm

_POOLS: dict[tuple, ProcessPoolExecutor] = {}
_WORKER: dict = {}  # inside a worker: its runner, and its envs with the pickled factory they came from


def threads_per_worker(workers: int) -> int:
    """torch threads for each of ``workers`` processes: the cores shared out, at least one each."""
    return max(1, (os.cpu_count() or 1) // workers)


def _init_worker(policy_path: str, device: str, overrides: dict, threads: int) -> None:
    import torch

    from lerobot_suture.runtime.policy import GateMode, PolicyRunner

    torch.set_num_threads(threads)
    _WORKER["runner"] = PolicyRunner.from_pretrained(policy_path, GateMode.REPORT, device, overrides)


def _run_batch(rollout_episodes: Callable, factory: bytes, gate, seeds: list[int], surgeon: str) -> list:
    if _WORKER.get("factory") != factory or len(_WORKER["envs"]) < len(seeds):
        for env in _WORKER.get("envs", []):
            env.close()
        make_env = pickle.loads(factory)
        _WORKER["envs"] = [make_env() for _ in seeds]
        _WORKER["factory"] = factory
    runner = _WORKER["runner"].with_gate(gate)
    return rollout_episodes(_WORKER["envs"][: len(seeds)], runner, seeds, surgeon)


def directory_state(policy_path: str) -> tuple:
    """What the workers loaded from: every file of the policy directory, with its size and time."""
    files = sorted(p for p in Path(policy_path).iterdir() if p.is_file())
    return tuple((p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in files)


def _pool(policy_path: str, device: str, overrides: dict, workers: int) -> ProcessPoolExecutor:
    key = (policy_path, device, tuple(sorted(overrides.items())), workers, directory_state(policy_path))
    if key not in _POOLS:
        shutdown_pools()  # another policy's workers: free their memory first
        _POOLS[key] = ProcessPoolExecutor(
            max_workers=workers,
            mp_context=multiprocessing.get_context("spawn"),  # no forked torch threads or GL contexts
            initializer=_init_worker,
            initargs=(policy_path, device, overrides, threads_per_worker(workers)),
        )
    return _POOLS[key]


@atexit.register
def shutdown_pools() -> None:
    """Stop every worker (also at exit)."""
    for pool in _POOLS.values():
        pool.shutdown(cancel_futures=True)
    _POOLS.clear()


def rollout_in_workers(
    rollout_episodes: Callable,
    make_env: Callable,
    runner,
    seeds: Sequence[int],
    batch_envs: int,
    surgeon: str,
    workers: int,
    desc: str | None,
) -> list:
    """:func:`~lerobot_suture.runtime.rollout.rollout_seeds` with the batches spread over ``workers``
    processes; the logs come back in the order of ``seeds``. ``rollout_episodes`` is
    :func:`~lerobot_suture.runtime.rollout.rollout_episodes`, handed over (by reference) so that this module
    does not import the one that imports it.

    Raises:
        ValueError: ``runner`` was not loaded from a directory (``PolicyRunner.from_pretrained``), or
            ``make_env`` cannot be pickled (a lambda: pass ``functools.partial(make_scenario_env, ...)``).
    """
    source = getattr(runner, "source", None)
    if source is None:
        raise ValueError(
            "`workers` > 1 needs a runner loaded with PolicyRunner.from_pretrained (each worker loads the policy "
            "from its directory); run this one with workers=1."
        )
    try:
        factory = pickle.dumps(make_env)
    except (pickle.PicklingError, AttributeError, TypeError) as error:
        raise ValueError(
            f"`workers` > 1 needs an env factory that can be pickled; got {make_env!r} ({error}). Pass "
            "functools.partial(make_scenario_env, ...) instead of a lambda."
        ) from None
    pool = _pool(str(source[0]), source[1], source[2], workers)
    batches = [list(seeds[i : i + batch_envs]) for i in range(0, len(seeds), batch_envs)]
    futures = {
        pool.submit(_run_batch, rollout_episodes, factory, runner.gate, batch, surgeon): k
        for k, batch in enumerate(batches)
    }
    results: list = [None] * len(batches)
    with tqdm(total=len(seeds), desc=desc, unit="episode") as progress:
        for future in as_completed(futures):
            k = futures[future]
            results[k] = future.result()
            progress.update(len(batches[k]))
    return [log for batch in results for log in batch]
