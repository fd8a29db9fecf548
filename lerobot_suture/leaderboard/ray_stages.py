"""A pipeline's stages as Ray tasks: each runs where a node has the cores (and GPUs) it asks for, once the
stages whose results it takes have finished.

One machine is the default: with no address, the first :class:`StageGraph` starts a Ray instance on this
machine for the process (nothing to start beforehand). An address (``HOST:PORT`` of ``ray start --head``,
or ``auto``) runs the stages on that cluster instead; every node needs lerobot-suture installed and the
run's directories at the same paths (a shared filesystem), because the stages hand each other datasets,
checkpoints and cells as files.

A stage's outputs are files written whole, so a stage is done once: run again, it reads them back. A
worker or node that dies mid-stage loses that stage only; Ray runs it again on a live node (``max_retries``),
and a stage that still fails is reported at the end, after every stage that did not need it has finished.

Where Ray would cost more than it saves, the home-made pool of :mod:`lerobot_suture.runtime.workers` stays:
one evaluation in one command (``lerobot-suture experiments``, ``calibrate``, ``dagger``) keeps one copy of
the policy per process across all its batches, without a Ray instance's start (seconds) and memory.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass

from tqdm import tqdm

logger = logging.getLogger(__name__)

MAX_RETRIES = 3
"""Times Ray runs a stage again after its worker or node died (not after the stage raised)."""


class ProgressBoard:
    """A Ray actor (no cores): the stages running now, each with the time it started."""

    def __init__(self):
        self.running: dict[str, float] = {}

    def started(self, key: str) -> None:
        self.running[key] = time.time()

    def finished(self, key: str) -> None:
        self.running.pop(key, None)

    def snapshot(self) -> dict[str, float]:
        return dict(self.running)


def _run_stage(fn: Callable, progress, key: str, *args):
    """``fn(*args)`` inside a Ray worker, announced on the progress board; returns it and its wall time."""
    progress.started.remote(key)
    start = time.perf_counter()
    try:
        result = fn(*args)
    finally:
        progress.finished.remote(key)
    return result, time.perf_counter() - start


_CONNECTED: dict = {}  # the address this process's Ray connection was made with


def connect(address: str | None) -> dict:
    """Ray on ``address`` (None: an instance on this machine, started once per process); the cluster's
    resources. A ConnectionError names the address and how to start a cluster there."""
    import ray

    if ray.is_initialized():
        if _CONNECTED.get("address", address) == address:
            return ray.cluster_resources()
        ray.shutdown()
    _CONNECTED["address"] = address
    try:
        ray.init(address=address, include_dashboard=False, log_to_driver=False, logging_level=logging.WARNING)
    except ConnectionError as error:
        raise ConnectionError(
            f"No Ray cluster at --ray_address={address}: start one with `ray start --head` on the head node "
            "and `ray start --address=HEAD:6379` on the others, or leave --ray_address out to run on this "
            "machine. A cluster started by `ray start` checks a token: export RAY_AUTH_MODE=token, with the "
            f"head's ~/.ray/auth_token on this machine. ({error})"
        ) from error
    return ray.cluster_resources()


@dataclass
class StageGraph:
    """The stages of one run: :meth:`submit` each (its arguments may be other stages' results), then
    :meth:`run` waits for all of them with a progress bar."""

    address: str | None = None

    def __post_init__(self):
        import ray
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        self.kinds: dict[str, str] = {}  # stage key -> kind ("record", "cell", ...)
        self.cpus: dict[str, float] = {}  # stage key -> the cores it holds
        self.resources = connect(self.address)
        self._nodes_cpus = [n["Resources"].get("CPU", 0) for n in ray.nodes() if n["Alive"]]
        # On the driver's node: the board outlives any other node.
        here = NodeAffinitySchedulingStrategy(ray.get_runtime_context().get_node_id(), soft=False)
        self._progress = ray.remote(num_cpus=0)(ProgressBoard).options(scheduling_strategy=here).remote()
        self._refs: dict[str, tuple] = {}  # key -> (result ref, seconds ref)

    def submit(self, key: str, kind: str, fn: Callable, *args, cpus: float = 1, gpus: float = 0):
        """Run ``fn(*args)`` as a Ray task on ``cpus`` cores and ``gpus`` GPUs; its result's reference (pass
        it to another stage to run that one after it). A ValueError when no node has those cores."""
        import ray

        if key in self._refs:
            raise ValueError(f"Stage {key!r} was submitted twice.")
        if cpus > max(self._nodes_cpus, default=0):
            raise ValueError(
                f"Stage {key!r} asks for {cpus} cores; the largest node of the Ray cluster has "
                f"{max(self._nodes_cpus, default=0)}. Lower the request (e.g. --train_cpus) or add a larger node."
            )
        remote = ray.remote(_run_stage).options(
            num_cpus=cpus, num_gpus=gpus, num_returns=2, max_retries=MAX_RETRIES, name=key
        )
        result, seconds = remote.remote(fn, self._progress, key, *args)
        self._refs[key] = (result, seconds)
        self.kinds[key], self.cpus[key] = kind, cpus
        return result

    def run(self, desc: str, unit_kind: str = "cell") -> tuple[dict, dict[str, float], dict[str, str]]:
        """Wait for every stage; returns their results, their seconds, and the error of each stage that failed
        (a failed stage's dependents fail with it; the others run to the end)."""
        import ray

        pending = {refs[1]: key for key, refs in self._refs.items()}
        results, seconds, failures = {}, {}, {}
        units = sum(kind == unit_kind for kind in self.kinds.values())
        slots = max(1.0, self.resources.get("CPU", 1.0))
        with tqdm(total=units, desc=desc, unit=unit_kind) as bar:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1, timeout=2.0)
                for ref in done:
                    key = pending.pop(ref)
                    try:
                        seconds[key] = ray.get(ref)
                        results[key] = ray.get(self._refs[key][0])
                    except Exception as error:  # noqa: BLE001 - reported with the stage's key at the end
                        failures[key] = f"{type(error).__name__}: {str(error).splitlines()[0][:300]}"
                        logger.error("stage %s failed: %s", key, failures[key])
                    if self.kinds[key] == unit_kind:
                        bar.update(1)
                unfinished = list(pending.values())
                # A stage's "finished" may reach the board after its result reached this loop.
                running = {
                    k: t for k, t in ray.get(self._progress.snapshot.remote()).items() if k in unfinished
                }
                left = time_left(unfinished, self.kinds, self.cpus, seconds, running, slots)
                others = sorted(k for k in running if self.kinds[k] != unit_kind)[:2]
                cells_running = sum(self.kinds[k] == unit_kind for k in running)
                # Redrawn at every wait, so that a long training shows it is running.
                bar.set_postfix_str(
                    ", ".join([f"{cells_running} cells running", *others, f"left {_clock(left)}"])
                )
        return results, seconds, failures


def time_left(
    unfinished: list[str],
    kinds: dict[str, str],
    cpus: dict[str, float],
    seconds: dict[str, float],
    running: dict[str, float],
    slots: float,
    now: float | None = None,
) -> float | None:
    """Seconds until the unfinished stages are done, from the mean time of the finished stages of each kind:
    their core-seconds over the cluster's cores, less what the running ones have already done. None while
    a kind has no finished stage to go by."""
    now = time.time() if now is None else now
    mean: dict[str, list[float]] = defaultdict(list)
    for key, s in seconds.items():
        mean[kinds[key]].append(s)
    work = 0.0
    for key in unfinished:
        if not mean[kinds[key]]:
            return None
        expected = sum(mean[kinds[key]]) / len(mean[kinds[key]])
        done = now - running[key] if key in running else 0.0
        work += max(0.0, expected - done) * cpus[key]
    return work / slots


def _clock(s: float | None) -> str:
    if s is None:
        return "?"
    s = int(s)
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"
