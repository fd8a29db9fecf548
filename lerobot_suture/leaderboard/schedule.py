"""A pipeline's time on a cluster, projected from its stages' measured times.

:func:`makespan` list-schedules a graph of stages on ``machines`` nodes of ``cpus`` cores each the way Ray
places tasks: a stage starts as soon as the stages it reads have finished and one node has the cores it
asks for; among the stages ready at once, the one with the longest chain of work behind it starts first.
Pure: seconds in, seconds out.
"""

from __future__ import annotations

import heapq
from collections.abc import Sequence
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Stage:
    """One task of the graph: ``seconds`` of wall time on ``cpus`` cores, after every stage in ``after``."""

    key: str
    seconds: float
    cpus: int = 1
    after: tuple[str, ...] = field(default_factory=tuple)

    def __post_init__(self):
        if self.seconds < 0 or self.cpus < 1:
            raise ValueError(f"Stage {self.key!r}: seconds must be >= 0 and cpus >= 1. Got {self}.")


def _waiting(stages: dict[str, Stage]) -> dict[str, list[str]]:
    """For each stage, the stages that wait for it."""
    waiting: dict[str, list[str]] = {key: [] for key in stages}
    for stage in stages.values():
        for before in stage.after:
            waiting[before].append(stage.key)
    return waiting


def _chain_seconds(stages: dict[str, Stage], waiting: dict[str, list[str]]) -> dict[str, float]:
    """Each stage's own time plus the longest chain of stages that wait for it (its priority); a
    ValueError on a cycle."""
    left = {key: len(stage.after) for key, stage in stages.items()}
    order = [key for key, n in left.items() if n == 0]
    for key in order:  # grows as stages become ready: a topological order
        for after in waiting[key]:
            left[after] -= 1
            if left[after] == 0:
                order.append(after)
    if len(order) != len(stages):
        raise ValueError("The stages wait for each other in a cycle.")
    chain: dict[str, float] = {}
    for key in reversed(order):
        chain[key] = stages[key].seconds + max((chain[k] for k in waiting[key]), default=0.0)
    return chain


def makespan(graph: Sequence[Stage], machines: int, cpus: int) -> float:
    """Seconds from the first stage's start to the last one's end on ``machines`` nodes of ``cpus`` cores.

    Raises ValueError on a stage that no node can hold, an unknown dependency or a cycle.
    """
    if machines < 1 or cpus < 1:
        raise ValueError(f"machines and cpus must be >= 1. Got {machines}, {cpus}.")
    stages = {s.key: s for s in graph}
    if len(stages) != len(graph):
        raise ValueError("Stage keys must be unique.")
    for stage in graph:
        if stage.cpus > cpus:
            raise ValueError(f"Stage {stage.key!r} asks for {stage.cpus} cores; a node has {cpus}.")
        unknown = [k for k in stage.after if k not in stages]
        if unknown:
            raise ValueError(f"Stage {stage.key!r} waits for unknown stages {unknown}.")
    waiting = _waiting(stages)
    chain = _chain_seconds(stages, waiting)
    left = {key: len(stage.after) for key, stage in stages.items()}
    ready = [(-chain[k], k) for k, n in left.items() if n == 0]
    heapq.heapify(ready)
    free = [cpus] * machines
    running: list[tuple[float, str, int]] = []  # (end time, key, node)
    now = 0.0
    while ready or running:
        blocked = []
        while ready:
            priority, key = heapq.heappop(ready)
            need = stages[key].cpus
            node = next((i for i, f in enumerate(free) if f >= need), None)
            if node is None:
                blocked.append((priority, key))
                continue
            free[node] -= need
            heapq.heappush(running, (now + stages[key].seconds, key, node))
        for item in blocked:
            heapq.heappush(ready, item)
        now, key, node = heapq.heappop(running)
        free[node] += stages[key].cpus
        for after in waiting[key]:
            left[after] -= 1
            if left[after] == 0:
                heapq.heappush(ready, (-chain[after], after))
    return now
