"""The leaderboard's stages on Ray: the projection of a graph's time, the time left, and the board run on a
local cluster of two nodes, one of them killed mid-run."""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lerobot_suture.leaderboard.ray_stages import time_left
from lerobot_suture.leaderboard.schedule import Stage, makespan


def test_a_chain_takes_its_sum_and_independent_stages_their_longest():
    chain = [Stage("a", 3), Stage("b", 4, after=("a",)), Stage("c", 5, after=("b",))]
    assert makespan(chain, machines=4, cpus=2) == 12
    spread = [Stage(k, s) for k, s in zip("abcd", (1, 2, 3, 4), strict=True)]
    assert makespan(spread, machines=2, cpus=2) == 4
    assert makespan(spread, machines=1, cpus=1) == 10


def test_a_stage_waits_for_a_node_with_its_cores():
    # Two 2-core trainings and two 1-core cells on one 2-core node: no two trainings overlap.
    graph = [Stage("t1", 10, cpus=2), Stage("t2", 10, cpus=2), Stage("c1", 1), Stage("c2", 1)]
    assert makespan(graph, machines=1, cpus=2) == 21
    assert makespan(graph, machines=2, cpus=2) == 11


@pytest.mark.parametrize(
    "graph, match",
    [
        ([Stage("a", 1, cpus=4)], "asks for 4 cores"),
        ([Stage("a", 1, after=("z",))], "unknown stages"),
        ([Stage("a", 1, after=("b",)), Stage("b", 1, after=("a",))], "cycle"),
        ([Stage("a", 1), Stage("a", 2)], "unique"),
    ],
)
def test_a_graph_no_cluster_can_run_names_its_fault(graph, match):
    with pytest.raises(ValueError, match=match):
        makespan(graph, machines=2, cpus=2)


@st.composite
def graphs(draw):
    n = draw(st.integers(1, 12))
    stages = []
    for i in range(n):
        after = draw(st.lists(st.integers(0, i - 1), unique=True, max_size=3)) if i else []
        stages.append(Stage(str(i), draw(st.floats(0, 100)), after=tuple(str(a) for a in after)))
    return stages


@settings(max_examples=200, deadline=None)
@given(graphs(), st.integers(1, 4), st.integers(1, 3))
def test_the_projection_lies_between_the_bounds_of_list_scheduling(graph, machines, cpus):
    """At least the longest chain and the work over the cores; at most Graham's bound for list scheduling
    (work over cores plus the longest chain), and never more than running the stages one after another."""
    stages = {s.key: s for s in graph}
    chain: dict[str, float] = {}
    for s in graph:  # listed after the stages they wait for
        chain[s.key] = s.seconds + max((chain[a] for a in s.after), default=0.0)
    longest, work = max(chain.values()), sum(s.seconds for s in stages.values())
    span = makespan(graph, machines, cpus)
    slots = machines * cpus
    assert span >= max(longest, work / slots) - 1e-9
    assert span <= min(work, work / slots + longest) + 1e-9


def test_time_left_goes_by_the_finished_stages_of_each_kind():
    kinds = {"c1": "cell", "c2": "cell", "c3": "cell", "t": "train"}
    cpus = {"c1": 1, "c2": 1, "c3": 1, "t": 2}
    seconds = {"c1": 10.0}
    # c2 has run 4 s of the 10 a cell takes; c3 has not started: 6 + 10 core-seconds over 2 cores.
    assert time_left(["c2", "c3"], kinds, cpus, seconds, {"c2": 96.0}, slots=2, now=100.0) == 8.0
    assert time_left(["c2", "t"], kinds, cpus, seconds, {}, slots=2, now=100.0) is None  # no training yet


def _leaderboard(policy_dir: Path, work: Path, *extra: str, env: dict | None = None) -> subprocess.Popen:
    command = [
        str(Path(sys.executable).parent / "lerobot-suture"),
        "leaderboard",
        f"--policy.path={policy_dir}",
        "--policy_name=tiny",
        "--tasks=[insertion]",
        "--episodes=2",
        "--batch_envs=2",
        "--shifts=[]",
        f"--output_dir={work}",
        f"--results_dir={work / 'results'}",
        *extra,
    ]
    return subprocess.Popen(
        command,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, **(env or {})},
    )


def _per_episode(work: Path) -> dict:
    from lerobot_suture.leaderboard.cells import unpacked_episodes

    board = json.loads((work / "results" / "leaderboard.json").read_text())
    return {
        c: unpacked_episodes(cell["per_episode"]) for c, cell in board["tasks"]["insertion"]["tiny"].items()
    }


@pytest.mark.slow
def test_a_local_cluster_gives_the_same_episodes_and_a_dead_node_loses_no_finished_cell(
    tiny_policy_dir, tmp_path
):
    """A head and a second node on this machine (loopback only) run one task's row. The episodes are the
    ones a run on this machine alone gives; the second node killed mid-run loses no finished cell, and the
    board is complete after the run (Ray retries the lost cell) or a rerun."""
    from ray.cluster_utils import Cluster

    alone = _leaderboard(tiny_policy_dir, tmp_path / "alone")
    out, _ = alone.communicate(timeout=900)
    assert alone.returncode == 0, out[-3000:]
    expected = _per_episode(tmp_path / "alone")
    assert len(expected) == 5 and all(len(v) == 2 for v in expected.values())

    loopback = {"node_ip_address": "127.0.0.1", "num_cpus": 1}
    # A driver outside Ray's cluster mode keeps 127.0.0.1 (in cluster mode Ray swaps it for the host's address,
    # where a loopback cluster does not listen).
    driver = {"RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"}
    cluster = Cluster(initialize_head=True, head_node_args=loopback, shutdown_at_exit=True)
    try:
        second = cluster.add_node(**loopback)
        work = tmp_path / "cluster"
        run = _leaderboard(tiny_policy_dir, work, f"--ray_address={cluster.address}", env=driver)
        cells = work / "cells" / "insertion" / "tiny"
        deadline = time.time() + 600
        while not list(cells.glob("*.json")) and time.time() < deadline and run.poll() is None:
            time.sleep(0.5)
        finished = {f: f.stat().st_mtime_ns for f in cells.glob("*.json")}
        assert finished, "no cell finished before the deadline"
        assert run.poll() is None, "the run ended before the node could be killed"
        cluster.remove_node(second, allow_graceful=False)
        out, _ = run.communicate(timeout=900)
        if run.returncode != 0:  # the run may end with the lost cell failed: a rerun finishes it
            rerun = _leaderboard(tiny_policy_dir, work, f"--ray_address={cluster.address}", env=driver)
            out, _ = rerun.communicate(timeout=900)
            assert rerun.returncode == 0, out[-3000:]
        assert {f: f.stat().st_mtime_ns for f in finished} == finished  # never recomputed
        assert _per_episode(work) == expected
    finally:
        cluster.shutdown()
