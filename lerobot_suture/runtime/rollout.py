"""Run a policy in the suture env with the O.O.D. gate at the env step, and hand over to a surgeon.

Every control step the policy (through :class:`~lerobot_suture.runtime.policy.PolicyRunner`) proposes
an action and its gate reports the uncertainty score, the threshold and the decision. While the gate
holds control with the policy, the policy's action is executed. Once an enforced gate releases
control (the policy then returns a hold action), a surgeon stand-in takes over:

- ``none``: nobody; the arm holds its pose and waits;
- ``expert``: the scripted expert, reading privileged state, finishes the task from where it is.

With the gate in reporting mode (``GateMode.REPORT``, the paper's experiments) the policy keeps
control and the decisions are only logged. Whatever reaches the robot goes through the env's step,
so a CBF wrapper around the env filters the surgeon's actions too.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import gymnasium as gym
import numpy as np
import torch
from tqdm import tqdm

from lerobot_suture.expert import ScriptedExpert
from lerobot_suture.registration import MAX_EPISODE_STEPS
from lerobot_suture.runtime.gates import PolicyGates, SilentGates
from lerobot_suture.runtime.workers import rollout_in_workers
from lerobot_suture.sim.shifts import Shift, ShiftWrapper
from lerobot_suture.sim.tasks import DEFAULT_TASK, task_spec

if TYPE_CHECKING:
    from lerobot_suture.safety.cbf_config import CBFConfig

SURGEONS = ("none", "expert")
POLICY, SURGEON, HOLD = "policy", "surgeon", "hold"


@dataclass
class StepLog:
    """One control step: who acted, and what the gate and the env said."""

    score: float
    threshold: float
    ood: bool
    released: bool
    new_prediction: bool
    controller: str
    perturbed: bool
    needle_in_tissue: bool
    h: float = math.nan
    cbf_active: bool = False
    cbf_intervened: bool = False
    h_min_physics: float = math.nan  # the safe set's barrier over the step's physics steps, CBF on and traced
    throw_index: int = 0  # the running suture's throw under way (0-based); 0 in the one-throw tasks


@dataclass
class EpisodeLog:
    seed: int
    scenario: str
    success: bool = False
    steps: list[StepLog] = field(default_factory=list)
    handover_step: int | None = None
    handover_cause: str = (
        ""  # "gate" (the policy's gate released control) or "tissue_motion" (the CBF's premise)
    )
    tissue_strain: float = 0.0
    entry_error_m: float = math.inf  # where the tip entered, from the marked entry point (inf: never)
    exit_error_m: float = math.inf
    h_min_physics: float = math.nan
    throw_results: list[dict] = field(default_factory=list)  # the running suture's record of each throw

    @property
    def scores(self) -> np.ndarray:
        return np.array([s.score for s in self.steps])

    @property
    def onset_step(self) -> int | None:
        return next((k for k, s in enumerate(self.steps) if s.perturbed), None)

    @property
    def first_alarm_step(self) -> int | None:
        return next((k for k, s in enumerate(self.steps) if s.ood), None)

    @property
    def autonomous_success(self) -> bool:
        return self.success and self.handover_step is None


def make_scenario_env(
    env_kwargs: dict,
    scenario: str,
    cbf: CBFConfig | None = None,
    trace: bool = False,
    shift: Shift | None = None,
) -> gym.Env:
    """One suture env of ``scenario`` for policy rollouts: ``env_kwargs`` (what the policy reads, from
    :func:`~lerobot_suture.runtime.policy.env_kwargs_for_policy`), the CBF filter, the tip trace, and a
    distribution shift (:mod:`lerobot_suture.sim.shifts`) over it all. The env is made from the id of
    ``env_kwargs``' task (insertion when it names none), so its episodes run that task's length."""
    env = gym.make(
        task_spec(env_kwargs.get("task", DEFAULT_TASK)).gym_id,
        disable_env_checker=True,
        scenario=scenario,
        cbf=cbf,
        record_tip_trace=trace,
        **env_kwargs,
    )
    return env if shift is None else ShiftWrapper(env, shift)


def rollout_episode(
    env: gym.Env,
    runner,
    seed: int,
    surgeon: str = "none",
    max_steps: int | None = None,
    gates: SilentGates | None = None,
) -> EpisodeLog:
    """One episode of ``runner`` (a :class:`PolicyRunner`) in ``env`` with the surgeon stand-in.

    ``env`` may be wrapped in a :class:`~lerobot_suture.safety.cbf_wrapper.CBFActionWrapper`; when it
    records the needle tip's physics-rate trace, ``h_min_physics`` is the smallest barrier of the safe set
    (>= 0 above the tissue or in the wound's ellipsoid) over every physics step while the CBF was on.
    """
    return rollout_episodes([env], runner, [seed], surgeon, max_steps, gates)[0]


def rollout_episodes(
    envs: Sequence[gym.Env],
    runner,
    seeds: Sequence[int],
    surgeon: str = "none",
    max_steps: int | None = None,
    gates: SilentGates | None = None,
) -> list[EpisodeLog]:
    """``len(envs)`` episodes in lockstep, ``envs[i]`` reset with ``seeds[i]``: one batched policy call
    per control step (much cheaper per episode than one call each), one O.O.D. gate per env: ``gates``
    (:mod:`lerobot_suture.runtime.gates`), by default the policy's own.

    An env whose episode has ended is not stepped again; its last observation keeps its row of the
    batch. Each episode's diffusion noise comes from its own seed (:class:`PolicyRunner`), so a seed gives
    the same episode in any batch; torch's global RNG is seeded from ``seeds[0]`` for anything else.
    """
    if surgeon not in SURGEONS:
        raise ValueError(f"`surgeon` must be one of {SURGEONS}. Got {surgeon!r}.")
    if len(envs) != len(seeds) or not envs:
        raise ValueError(
            f"Need one seed per env and at least one env. Got {len(envs)} envs, {len(seeds)} seeds."
        )
    if max_steps is None:
        spec = envs[0].spec
        max_steps = spec.max_episode_steps if spec and spec.max_episode_steps else MAX_EPISODE_STEPS
    torch.manual_seed(int(seeds[0]))
    observations = [env.reset(seed=int(seed))[0] for env, seed in zip(envs, seeds, strict=True)]
    runner.reset(seeds=[int(seed) for seed in seeds])
    gates = PolicyGates(runner.policy) if gates is None else gates
    gates.reset(len(envs))
    tasks = [env.unwrapped.task_description for env in envs]  # each env's instruction, as lerobot-eval sends
    n = len(envs)
    experts = [ScriptedExpert() for _ in range(n)]
    logs = [
        EpisodeLog(seed=int(seed), scenario=env.unwrapped.scenario.config.name)
        for env, seed in zip(envs, seeds, strict=True)
    ]
    infos: list[dict] = [{} for _ in range(n)]
    statuses: list[dict] = [{} for _ in range(n)]
    held: list[np.ndarray | None] = [None] * n  # the action in force once the gate released control
    done = [False] * n
    for _ in range(max_steps):
        if all(done):
            break
        policy_acts = any(not done[i] and logs[i].handover_step is None for i in range(n))
        actions = runner.act_batch(observations, tasks) if policy_acts else None
        for i, (env, log) in enumerate(zip(envs, logs, strict=True)):
            if done[i]:
                continue
            if log.handover_step is None:
                action, controller = actions[i], POLICY
                statuses[i] = gates.status(i)
                if statuses[i]["released"]:
                    log.handover_step, log.handover_cause = len(log.steps), "gate"
                    held[i] = action  # the policy's hold action at the release
                    experts[i].reset(env)  # the expert works out where the task stands
            else:  # the released policy is not asked again
                statuses[i] = {**statuses[i], "new_prediction": False}
            if log.handover_step is not None:
                # Released: the arm holds the pose of the release, or the surgeon acts.
                if surgeon == "expert":
                    action, controller = experts[i].act(env), SURGEON
                else:
                    action, controller = held[i], HOLD
            observations[i], _, terminated, truncated, info = env.step(action)
            infos[i] = info
            log.steps.append(_step_log(statuses[i], controller, info))
            if info.get("cbf_guarding") and "needle_tip_trace" in info:
                log.steps[-1].h_min_physics = float(env.get_wrapper_attr("h_min")(info))
            if log.handover_step is None and info.get("cbf_motion_exceeded"):
                # The tissue moves beyond what the CBF was declared to cover: the surgeon takes over (or the arm
                # holds its measured pose, the filter still tracking the tissue).
                log.handover_step, log.handover_cause = len(log.steps), "tissue_motion"
                held[i] = np.asarray(observations[i]["agent_pos"], dtype=np.float32)
                experts[i].reset(env)
            done[i] = bool(terminated or truncated)
    for log, info in zip(logs, infos, strict=True):
        log.success = bool(info["is_success"])
        log.tissue_strain = float(info["tissue_strain"])
        log.entry_error_m = float(info["entry_error_m"])
        log.exit_error_m = float(info["exit_error_m"])
        log.h_min_physics = min(
            (s.h_min_physics for s in log.steps if not math.isnan(s.h_min_physics)), default=math.nan
        )
        log.throw_results = list(info.get("throw_results", []))
    return logs


def rollout_seeds(
    make_env: Callable[[], gym.Env],
    runner,
    seeds: Sequence[int],
    batch_envs: int = 8,
    surgeon: str = "none",
    desc: str | None = None,
    workers: int = 1,
    gates: SilentGates | None = None,
) -> list[EpisodeLog]:
    """One episode per seed, ``batch_envs`` at a time (:func:`rollout_episodes`), with a progress bar.

    ``make_env()`` builds one env; ``min(batch_envs, len(seeds))`` of them are built and reused. With
    ``workers`` > 1 the batches run in that many processes (:mod:`lerobot_suture.runtime.workers`; the
    runner must come from ``PolicyRunner.from_pretrained`` and ``make_env`` must pickle): the same
    episodes, sooner on several cores. ``gates``: as in :func:`rollout_episodes` (with one worker only).
    """
    if batch_envs < 1 or workers < 1:
        raise ValueError(f"`batch_envs` and `workers` must be >= 1. Got {batch_envs}, {workers}.")
    if gates is not None and workers > 1:
        raise ValueError("`gates` other than the policy's own run in this process only: pass `workers=1`.")
    seeds = [int(s) for s in seeds]
    if workers > 1 and len(seeds) > batch_envs:
        return rollout_in_workers(
            rollout_episodes, make_env, runner, seeds, batch_envs, surgeon, workers, desc
        )
    envs = [make_env() for _ in range(min(batch_envs, len(seeds)))]
    logs: list[EpisodeLog] = []
    try:
        with tqdm(total=len(seeds), desc=desc, unit="episode") as progress:
            for start in range(0, len(seeds), len(envs) or 1):
                chunk = seeds[start : start + len(envs)]
                logs += rollout_episodes(envs[: len(chunk)], runner, chunk, surgeon, gates=gates)
                progress.update(len(chunk))
    finally:
        for env in envs:
            env.close()
    return logs


def _step_log(status: dict, controller: str, info: dict) -> StepLog:
    return StepLog(
        score=status["score"],
        threshold=status["threshold"],
        ood=status["decision"],
        released=status["released"],
        new_prediction=status["new_prediction"],
        controller=controller,
        perturbed=bool(info["perturbed"]),
        needle_in_tissue=bool(info["needle_in_tissue"]),
        h=float(info.get("h", math.nan)),
        cbf_active=bool(info.get("cbf_active", False)),
        cbf_intervened=bool(info.get("cbf_intervened", False)),
        throw_index=int(info.get("throw_index", 0)),
    )
