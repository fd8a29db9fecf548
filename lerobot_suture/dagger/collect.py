"""New labelled frames for one round of one arm, written as a LeRobotDataset that merges with the demonstrations.

Every arm rolls out in the same scenarios on the same fresh seeds, and every frame is built as
:class:`~lerobot_suture.surgeon.record_run.RunRecorder` builds a surgeon run's (the demonstrations' features:
endoscope image, state, needle keypoints in the image, action, reward, success, done; plus the four
``complementary_info`` labels), so the three arms' data and the labelled demonstrations merge. Frames are
kept in memory per episode, selected, then written. What each arm labels:

========== ==================================================== ============================================
arm        the rollout                                          the frames kept, and their ``action``
========== ==================================================== ============================================
gated      the policy with its gate enforced; once the gate     only the surgeon's (``actor`` 1,
           releases control the surgeon stand-in (the           ``is_intervention`` 1), each contiguous run
           privileged expert) finishes from where it is; with   of them an episode; ``action``: the
           ``watch`` it also takes over on its own when the     surgeon's executed action
           policy's commands stray (:mod:`~lerobot_suture.
           dagger.watch`)
ungated    the policy drives every step (the gate reports);     every visited state (``actor`` 0,
           beside it the expert, its phase placed on the state  ``is_intervention`` 0, the gate's score and
           the policy reached (:mod:`~lerobot_suture.dagger.    decision), then a contiguous window per
           labelling`), is asked for its action at each         episode, the budget spread evenly over the
           visited state                                        episodes; ``action``: the expert's label,
                                                                not the executed action
bc         the expert alone from the start, as ``lerobot-suture successful episodes whole, in order with the
           record`` records (failed attempts discarded)         scenarios interleaved, the last one cut;
                                                                labelled as the demonstrations (``actor`` 1,
                                                                ``is_intervention`` 0, score NaN, gate -1)
========== ==================================================== ============================================

The expert everywhere is the one that recorded the demonstrations (its settings from the dataset's episode
log), so the new labels and the demonstrations agree. The ``ungated`` and ``bc`` arms keep as many frames as
the ``gated`` arm's surgeon gave that round (the budget), or all they have when that is fewer.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from lerobot_suture.dagger.labelling import StateLabeller
from lerobot_suture.dagger.watch import WatchConfig, WatchingExpertSurgeon
from lerobot_suture.expert import ExpertConfig, ScriptedExpert
from lerobot_suture.runtime.policy import GateMode
from lerobot_suture.runtime.takeover import Actor
from lerobot_suture.surgeon.record_run import (
    ACTOR_KEY,
    GATE_DECISION_KEY,
    IS_INTERVENTION_KEY,
    NOT_CONSULTED,
    RunRecorder,
    labels,
)

logger = logging.getLogger(__name__)

_BC_ATTEMPTS_PER_EPISODE = 10  # expert attempts per scenario at most, per collected policy episode


@dataclass(frozen=True)
class CollectSpec:
    """Where and how a round collects: the same for every arm.

    Args:
        env_kwargs: the env's arguments (observation layout the policy reads, grasp, appearance).
        seeds: scenario -> env seeds of the round's episodes in it.
        expert_config: the demonstrations' expert.
        steps_after_success: control steps the demonstrations go on past success (the ``bc`` arm's too).
        video: store the endoscope as MP4 (as the demonstrations do) or PNG frames.
        watch: whether and when the gated arm's surgeon stand-in takes over on its own
            (:mod:`~lerobot_suture.dagger.watch`).
    """

    env_kwargs: dict
    seeds: dict[str, list[int]]
    expert_config: ExpertConfig
    steps_after_success: int = 0
    video: bool = True
    watch: WatchConfig = field(default_factory=WatchConfig)


class EpisodeBuffer:
    """The part of ``LeRobotDataset`` a :class:`RunRecorder` writes to, kept in memory: frames per episode."""

    def __init__(self):
        self.episodes: list[list[dict]] = []
        self._current: list[dict] = []

    def add_frame(self, frame: dict) -> None:
        self._current.append(frame)

    def save_episode(self) -> None:
        self.episodes.append(self._current)
        self._current = []

    def clear_episode_buffer(self) -> None:
        self._current = []

    def finalize(self) -> None:
        pass


class BufferedRecorder(RunRecorder):
    """:class:`RunRecorder`'s frames, buffered per episode instead of written (they are selected first)."""

    def __init__(self):  # no dataset on disk
        self._keypoints = None
        self.dataset = EpisodeBuffer()


class LabellingRecorder(BufferedRecorder):
    """Records, at every step, the expert's action at the visited state in place of the executed one
    (:class:`~lerobot_suture.dagger.labelling.StateLabeller`, reset at each episode's first state)."""

    def __init__(self, expert_config: ExpertConfig):
        super().__init__()
        self.labeller = StateLabeller(expert_config)
        self._label: np.ndarray | None = None
        self._new_episode = True

    def observe(self, env) -> None:
        super().observe(env)
        if self._new_episode:
            self.labeller.reset(env)
            self._new_episode = False
        self._label = self.labeller.label(env)

    def add(self, env, observation, action, reward, info, done, actor, score, decision) -> None:
        super().add(env, observation, self._label, reward, info, done, actor, score, decision)

    def save_episode(self) -> None:
        super().save_episode()
        self._new_episode = True


# ------------------------------------------------------------------ selection (pure)


def surgeon_segments(frames: list[dict]) -> list[list[dict]]:
    """The contiguous runs of surgeon frames (``actor`` 1) of one episode, each a new episode."""
    segments: list[list[dict]] = []
    previous = False
    for frame in frames:
        surgeon = int(frame[ACTOR_KEY][0]) == int(Actor.SURGEON)
        if surgeon and not previous:
            segments.append([])
        if surgeon:
            segments[-1].append(frame)
        previous = surgeon
    return segments


def spread_budget(lengths: list[int], budget: int) -> list[int]:
    """Frames per episode, as even as the episodes' lengths allow, summing to ``min(budget, sum(lengths))``.

    Water filling: every episode gets an equal share, capped by its length, and what a short episode
    cannot take goes to the others; the remainder goes to the first episodes with room.
    """
    if budget < 0:
        raise ValueError(f"`budget` must be >= 0. Got {budget}.")
    take = [0] * len(lengths)
    left = min(budget, sum(lengths))
    open_ = [i for i, n in enumerate(lengths) if n > 0]
    while left > 0 and open_:
        share = max(1, left // len(open_))
        for i in list(open_):
            add = min(share, lengths[i] - take[i], left)
            take[i] += add
            left -= add
            if take[i] == lengths[i]:
                open_.remove(i)
            if left == 0:
                break
    return take


def windows(episodes: list[list[dict]], budget: int, seed: int) -> list[list[dict]]:
    """A contiguous window of each episode (:func:`spread_budget` long, at a seeded random start)."""
    rng = np.random.default_rng(seed)
    kept = []
    for frames, n in zip(episodes, spread_budget([len(e) for e in episodes], budget), strict=True):
        if n:
            start = int(rng.integers(0, len(frames) - n + 1))
            kept.append(frames[start : start + n])
    return kept


def truncate(episodes: list[list[dict]], budget: int) -> list[list[dict]]:
    """Whole episodes in order until ``budget`` frames, the last one cut."""
    kept, left = [], budget
    for frames in episodes:
        if left <= 0:
            break
        kept.append(frames[:left])
        left -= len(kept[-1])
    return kept


def frame_count(episodes: list[list[dict]]) -> int:
    return sum(len(e) for e in episodes)


# ------------------------------------------------------------------ the arms' rollouts


def _env(spec: CollectSpec, scenario: str):
    from lerobot_suture.runtime.rollout import make_scenario_env

    return make_scenario_env(spec.env_kwargs, scenario)


def _policy_runs(runner, spec: CollectSpec, surgeon, recorder, desc: str) -> list[dict]:
    """One policy episode per seed and scenario through the surgeon session; returns a summary per episode."""
    from lerobot_suture.registration import MAX_EPISODE_STEPS
    from lerobot_suture.surgeon.session import run_surgeon_episode

    summaries = []
    total = sum(len(s) for s in spec.seeds.values())
    with tqdm(total=total, desc=desc, unit="episode") as progress:
        for scenario, seeds in spec.seeds.items():
            env = _env(spec, scenario)
            try:
                for seed in seeds:
                    log = run_surgeon_episode(
                        env, runner, surgeon, seed, MAX_EPISODE_STEPS, recorder=recorder
                    )
                    summaries.append(
                        {
                            "scenario": scenario,
                            "seed": seed,
                            "success": log.success,
                            "steps": len(log.steps),
                            "handover_step": log.handovers[0][0] if log.handovers else None,
                            "handover_reason": log.handovers[0][3] if log.handovers else None,
                            "surgeon_steps": sum(a is Actor.SURGEON for a in log.actors),
                        }
                    )
                    progress.update(1)
            finally:
                env.close()
    return summaries


def collect_gated(runner, spec: CollectSpec) -> tuple[list[list[dict]], list[dict]]:
    """The gated arm: gate enforced, the expert surgeon after the handover (or after its own takeover when
    it watches); only the surgeon's frames."""
    from lerobot_suture.surgeon.surgeons import ExpertSurgeon

    runner = runner.with_gate(GateMode.ENFORCE)
    recorder = BufferedRecorder()
    if spec.watch.enabled:
        surgeon = WatchingExpertSurgeon(spec.expert_config, spec.watch)
    else:
        surgeon = ExpertSurgeon(ScriptedExpert(spec.expert_config))
    runs = _policy_runs(runner, spec, surgeon, recorder, "gated")
    episodes = [seg for frames in recorder.dataset.episodes for seg in surgeon_segments(frames)]
    return episodes, runs


def collect_ungated(runner, spec: CollectSpec, budget: int, seed: int) -> tuple[list[list[dict]], list[dict]]:
    """The ungated arm: the policy drives, the expert labels every visited state; ``budget`` frames kept."""
    from lerobot_suture.surgeon.surgeons import NoSurgeon

    if budget == 0:  # nothing to label this round
        return [], []
    runner = runner.with_gate(GateMode.REPORT)
    recorder = LabellingRecorder(spec.expert_config)
    runs = _policy_runs(runner, spec, NoSurgeon(), recorder, "ungated")
    return windows(recorder.dataset.episodes, budget, seed), runs


def collect_bc(spec: CollectSpec, budget: int) -> tuple[list[list[dict]], list[dict]]:
    """The bc arm: whole expert demonstrations, scenarios interleaved, until ``budget`` frames."""
    from lerobot_suture.datasets.expert_episode import expert_episode_frames

    envs = {scenario: _env(spec, scenario) for scenario in spec.seeds}
    rounds = max(len(s) for s in spec.seeds.values()) * _BC_ATTEMPTS_PER_EPISODE
    episodes: list[list[dict]] = []
    runs: list[dict] = []
    expert = ScriptedExpert(spec.expert_config)
    try:
        with tqdm(total=budget, desc="bc", unit="frame") as progress:
            for k in range(rounds):
                for scenario, env in envs.items():
                    if frame_count(episodes) >= budget:
                        break
                    seed = _extra_seed(spec.seeds[scenario], k)
                    rollout = expert_episode_frames(
                        env, expert, seed, steps_after_success=spec.steps_after_success
                    )
                    runs.append(
                        {
                            "scenario": scenario,
                            "seed": seed,
                            "success": rollout.success,
                            "steps": rollout.length,
                        }
                    )
                    if rollout.success:
                        frames = [{**f, **demonstration_labels()} for f in rollout.frames]
                        episodes.append(frames)
                        progress.update(min(len(frames), budget - progress.n))
                if frame_count(episodes) >= budget:
                    break
    finally:
        for env in envs.values():
            env.close()
    return truncate(episodes, budget), runs


def _extra_seed(seeds: list[int], k: int) -> int:
    """The k-th seed of a scenario's run: its own seeds first, then the ones after the last."""
    return seeds[k] if k < len(seeds) else seeds[-1] + 1 + k - len(seeds)


def demonstration_labels() -> dict[str, np.ndarray]:
    """The label columns of a demonstration frame, as ``label_demonstrations`` writes them."""
    return {**labels(Actor.SURGEON, math.nan, NOT_CONSULTED), IS_INTERVENTION_KEY: np.zeros(1, np.float32)}


# ------------------------------------------------------------------ writing


def write_episodes(episodes: list[list[dict]], root: Path, repo_id: str, spec: CollectSpec) -> Path | None:
    """The episodes as a LeRobotDataset at ``root`` (LeRobot's writer through :class:`RunRecorder`);
    None, and nothing written, when there are no frames."""
    episodes = [e for e in episodes if e]
    if not episodes:
        return None
    recorder = RunRecorder(
        repo_id, root, spec.env_kwargs["obs_type"], spec.env_kwargs.get("image_size", 96), spec.video
    )
    for frames in tqdm(episodes, desc=f"writing {root.name}", unit="episode"):
        for frame in frames:
            recorder.dataset.add_frame(dict(frame))  # LeRobot's add_frame consumes its frame
        recorder.save_episode()
    recorder.finalize()
    return root


def label_counts(episodes: list[list[dict]]) -> dict:
    """Frames by actor, interventions and O.O.D. decisions among the frames kept (for the round's record)."""
    frames = [f for e in episodes for f in e]
    return {
        "episodes": len(episodes),
        "frames": len(frames),
        "interventions": int(sum(float(f[IS_INTERVENTION_KEY][0]) for f in frames)),
        "by_actor": {a.name.lower(): sum(int(f[ACTOR_KEY][0]) == int(a) for f in frames) for a in Actor},
        "gate_ood": sum(int(f[GATE_DECISION_KEY][0]) == 1 for f in frames),
    }
