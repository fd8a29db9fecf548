"""The one episode loop of the env path: a policy in the suture env with its O.O.D. gate, and a surgeon who can
take over.

Every control step each env's surgeon is polled (take over, hand back); while the policy is in control it
proposes an action (one batched call for every env, through
:class:`~lerobot_suture.runtime.policy.PolicyRunner`) and its gate (:mod:`lerobot_suture.runtime.gates`)
reports the score, the threshold and the decision; a scripted surgeon may take over on seeing the action,
before it runs. :class:`~lerobot_suture.runtime.takeover.Takeover` names the step's actor: an enforced gate that
releases control (the policy then returns a hold action), or tissue that moves beyond the CBF's premise, hands
it to the surgeon, or to a hold of the released pose when nobody is there. The policy is not asked while it is
out of control (its score is then NaN); a hand-back resets it, re-arming its gate. The surgeons:

- ``none``: nobody; the arm holds its pose and waits;
- ``expert``: the scripted expert, reading privileged state, finishes the task from where it is;
- ``expert_per_subtask``: the scripted expert takes over the running suture's subtask under way and hands back
  when it is done (with :class:`~lerobot_suture.runtime.gates.StageGates`: a gate per stage, enforced);
- any surgeon object (:mod:`lerobot_suture.surgeon.surgeons`: LeRobot's keyboard or gamepad), one per env.

With the gate in reporting mode (``GateMode.REPORT``, the paper's experiments) the policy keeps
control and the decisions are only logged. Whatever reaches the robot goes through the env's step,
so a CBF wrapper around the env filters the surgeon's actions too. :class:`EpisodeHooks` see every step
(recording, a live view, a scripted input); LeRobot's teleop events (success, quit, re-record) end an episode.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import gymnasium as gym
import numpy as np
import torch
from lerobot.teleoperators.utils import TeleopEvents
from tqdm import tqdm

from lerobot_suture.runtime.gates import PolicyGates, SilentGates
from lerobot_suture.runtime.takeover import (
    GATE_RELEASED,
    TAKEN_OVER,
    TISSUE_MOTION,
    Actor,
    ExpertSurgeon,
    NoSurgeon,
    SubtaskExpertSurgeon,
    Takeover,
)
from lerobot_suture.runtime.workers import rollout_in_workers
from lerobot_suture.sim.relative_actions import env_action, find_relative_actions
from lerobot_suture.sim.shifts import Shift, ShiftWrapper
from lerobot_suture.sim.tasks import DEFAULT_TASK, task_spec

if TYPE_CHECKING:
    from lerobot_suture.safety.cbf_config import CBFConfig

SURGEONS = ("none", "expert", "expert_per_subtask")
POLICY, SURGEON, HOLD = "policy", "surgeon", "hold"
CONTROLLERS = {Actor.POLICY: POLICY, Actor.SURGEON: SURGEON, Actor.HOLD: HOLD}
HANDOVER_CAUSES = {GATE_RELEASED: "gate", TISSUE_MOTION: "tissue_motion", TAKEN_OVER: "surgeon"}
NOT_ASKED = {
    "score": math.nan,
    "threshold": math.nan,
    "decision": False,
    "released": False,
    "new_prediction": False,
}
"""A step's gate status while the policy is out of control: it is not asked."""


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
    # The policy was asked this step: its gate's score, threshold and decision are real.
    consulted: bool = True
    subtask: str = ""  # the running suture's subtask the high level read (StageGates), else ""

    @property
    def actor(self) -> Actor:
        return next(a for a, name in CONTROLLERS.items() if name == self.controller)


@dataclass
class EpisodeLog:
    seed: int
    scenario: str
    success: bool = False
    steps: list[StepLog] = field(default_factory=list)
    handover_step: int | None = None
    # "gate" (the gate released control), "tissue_motion" (the CBF's premise), "surgeon" (taken over)
    handover_cause: str = ""
    handovers: list[tuple[int, Actor, Actor, str]] = field(default_factory=list)  # (step, from, to, why), all
    stop_reason: str = ""  # "env" (the episode ended), "max_steps", "teleop event" or "rerecord"
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

    @property
    def actors(self) -> list[Actor]:
        return [s.actor for s in self.steps]


class EpisodeHooks:
    """What sees every step of :func:`rollout_episodes` besides the loop (all no-ops here): a recorder, a live
    view, a scripted input. ``row`` is the env's index in the batch."""

    def before_poll(self, row: int, step: int) -> None:
        """Before the surgeon of env ``row`` is polled at ``step`` (a scripted input presses its keys)."""

    def after_poll(self, row: int, step: int) -> None:
        """After the poll (a scripted input releases its keys)."""

    def before_step(self, row: int, step: int, env, observation: dict, actor: Actor, log: StepLog) -> None:
        """Once the step's actor and action are known, before the env steps (``log`` without the env's say)."""

    def after_step(
        self, row: int, env, observation: dict, action, reward, info: dict, done: bool, log: StepLog
    ) -> None:
        """After the env stepped from ``observation`` with ``action``."""

    def end_episode(self, row: int, log: EpisodeLog, rerecord: bool) -> None:
        """The episode of env ``row`` ended (``rerecord``: a teleop event asked to record it again)."""


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
    surgeon: str | Sequence = "none",
    max_steps: int | None = None,
    gates: SilentGates | None = None,
    hooks: EpisodeHooks | None = None,
) -> list[EpisodeLog]:
    """``len(envs)`` episodes in lockstep, ``envs[i]`` reset with ``seeds[i]``: one batched policy call
    per control step (much cheaper per episode than one call each), one O.O.D. gate per env: ``gates``
    (:mod:`lerobot_suture.runtime.gates`), by default the policy's own.

    ``surgeon``: ``none``, ``expert`` (a stand-in per env), or one surgeon object per env. An env whose episode
    has ended is not stepped again; its last observation keeps its row of the batch. Each episode's diffusion
    noise comes from its own seed (:class:`PolicyRunner`), so a seed gives the same episode in any batch;
    torch's global RNG is seeded from ``seeds[0]`` for anything else. A hand-back resets the policy, so it needs
    one env per call. ``runner`` None: no policy, the surgeon drives every step (``lerobot-suture teleop``).
    """
    if len(envs) != len(seeds) or not envs:
        raise ValueError(
            f"Need one seed per env and at least one env. Got {len(envs)} envs, {len(seeds)} seeds."
        )
    n = len(envs)
    surgeons = _surgeons(surgeon, n)
    if runner is None and not all(person.present for person in surgeons):
        raise ValueError("Without a policy a surgeon must drive: pass a teleoperator's surgeon.")
    if max_steps is None:  # the env's own limit, else its task's (an env made without gym.make has no spec)
        spec = envs[0].spec
        task = getattr(envs[0].unwrapped, "task_name", DEFAULT_TASK)
        max_steps = (
            spec.max_episode_steps if spec and spec.max_episode_steps else task_spec(task).max_episode_steps
        )
    hooks = hooks or EpisodeHooks()
    torch.manual_seed(int(seeds[0]))
    observations = [env.reset(seed=int(seed))[0] for env, seed in zip(envs, seeds, strict=True)]
    if runner is not None:
        runner.reset(seeds=[int(seed) for seed in seeds])
    gates = (PolicyGates(runner.policy) if runner is not None else SilentGates()) if gates is None else gates
    own_gates = isinstance(gates, PolicyGates)  # an enforced gate of the policy's own makes it hold its pose
    gates.reset(n)
    tasks = [env.unwrapped.task_description for env in envs]  # each env's instruction, as lerobot-eval sends
    takeovers = [Takeover(has_surgeon=person.present) for person in surgeons]
    for env, person, takeover, observation in zip(envs, surgeons, takeovers, observations, strict=True):
        person.begin_episode(env)
        if runner is None:  # no policy: the surgeon drives from the first step
            takeover.actor = Actor.SURGEON
            person.take_control(env, observation)
    logs = [
        EpisodeLog(seed=int(seed), scenario=env.unwrapped.scenario.config.name)
        for env, seed in zip(envs, seeds, strict=True)
    ]
    infos: list[dict] = [{} for _ in range(n)]
    held: list[np.ndarray | None] = [None] * n  # the action in force while the arm holds
    done = [False] * n
    for step in range(max_steps):
        if all(done):
            break
        commands = {}
        for i in range(n):
            if not done[i]:
                gates.observe(i, observations[i])
                hooks.before_poll(i, step)
                commands[i] = surgeons[i].poll()
                hooks.after_poll(i, step)
        asked = [
            i in commands
            and takeovers[i].actor is Actor.POLICY
            and not (commands[i].take_over and surgeons[i].present)
            for i in range(n)
        ]
        actions = runner.act_batch(observations, tasks) if any(asked) else None
        for i, (env, log, takeover, person) in enumerate(zip(envs, logs, takeovers, surgeons, strict=True)):
            if done[i]:
                continue
            command, before, status, action = commands[i], takeover.actor, NOT_ASKED, None
            if asked[i]:
                action, status = actions[i], gates.status(i)
                if person.intervenes(env, action):
                    command = dataclasses.replace(command, take_over=True)
            actor = takeover.update(
                step, released=status["released"], take_over=command.take_over, hand_back=command.hand_back
            )
            if actor is Actor.POLICY and before is not Actor.POLICY:
                if n > 1:
                    raise RuntimeError(
                        "A hand-back resets the policy: run episodes with a surgeon one env at a time."
                    )
                runner.reset(seeds=[int(seeds[i])])  # re-armed: a fresh start from this observation
                gates.rearm(i)
                action, status = runner.act_batch(observations, tasks)[0], gates.status(0)
            elif actor is Actor.SURGEON:
                if before is not Actor.SURGEON:
                    person.take_control(env, observations[i])
                action = env_action(env, person.act(env, command))  # a surgeon acts in absolute poses
            elif actor is Actor.HOLD:
                if before is not Actor.HOLD:  # the policy's own hold action, or the measured pose
                    # A relative action repeated keeps moving: with relative actions the hold is the measured pose's.
                    relative = find_relative_actions(env) is not None
                    held[i] = (
                        action
                        if own_gates and not relative
                        else env_action(env, observations[i]["agent_pos"])
                    )
                action = held[i]
            _note_handover(log, takeover)
            step_log = _step_log(status, CONTROLLERS[actor], status is not NOT_ASKED)
            step_log.subtask = str(gates.context(i).get("subtask", ""))
            hooks.before_step(i, step, env, observations[i], actor, step_log)
            observation, reward, terminated, truncated, info = env.step(action)
            infos[i] = info
            _add_env_record(step_log, info)
            log.steps.append(step_log)
            if info.get("cbf_guarding") and "needle_tip_trace" in info:
                step_log.h_min_physics = float(env.get_wrapper_attr("h_min")(info))
            done[i] = bool(terminated or truncated)
            hooks.after_step(i, env, observations[i], action, reward, info, done[i], step_log)
            observations[i] = observation
            if info.get("cbf_motion_exceeded") and takeover.actor is Actor.POLICY:
                # The tissue moves beyond what the CBF was declared to cover: the surgeon takes over (or the arm
                # holds its measured pose, the filter still tracking the tissue).
                if takeover.tissue_moved(len(log.steps)) is Actor.SURGEON:
                    person.take_control(env, observation)
                held[i] = np.asarray(observation["agent_pos"], dtype=np.float32)
                _note_handover(log, takeover)
            events = command.events
            rerecord = bool(events.get(TeleopEvents.RERECORD_EPISODE, False))
            ended = events.get(TeleopEvents.TERMINATE_EPISODE) or events.get(TeleopEvents.SUCCESS)
            if done[i] or rerecord or ended:
                log.stop_reason = "env" if done[i] else "rerecord" if rerecord else "teleop event"
                done[i] = True
    for i, (log, info, takeover) in enumerate(zip(logs, infos, takeovers, strict=True)):
        log.stop_reason = log.stop_reason or "max_steps"
        log.handovers = list(takeover.handovers)
        log.success = bool(info["is_success"])
        log.tissue_strain = float(info["tissue_strain"])
        log.entry_error_m = float(info["entry_error_m"])
        log.exit_error_m = float(info["exit_error_m"])
        log.h_min_physics = min(
            (s.h_min_physics for s in log.steps if not math.isnan(s.h_min_physics)), default=math.nan
        )
        log.throw_results = list(info.get("throw_results", []))
        hooks.end_episode(i, log, log.stop_reason == "rerecord")
    return logs


def _surgeons(surgeon, n: int) -> list:
    """One surgeon per env: ``none``, ``expert`` (a stand-in each), or the given objects."""
    if isinstance(surgeon, str):
        if surgeon not in SURGEONS:
            raise ValueError(f"`surgeon` must be one of {SURGEONS}. Got {surgeon!r}.")
        stand_in = {"none": NoSurgeon, "expert": ExpertSurgeon, "expert_per_subtask": SubtaskExpertSurgeon}[
            surgeon
        ]
        return [stand_in() for _ in range(n)]
    surgeons = list(surgeon)
    if len(surgeons) != n:
        raise ValueError(f"Need one surgeon per env. Got {len(surgeons)} surgeons for {n} envs.")
    return surgeons


def _note_handover(log: EpisodeLog, takeover: Takeover) -> None:
    """The episode's first handover: its step and why."""
    if log.handover_step is None and takeover.handovers:
        step, _, _, why = takeover.handovers[0]
        log.handover_step, log.handover_cause = step, HANDOVER_CAUSES[why]


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


def _step_log(status: dict, controller: str, consulted: bool) -> StepLog:
    """A step's log before the env steps: the gate's status and who acts."""
    return StepLog(
        score=float(status["score"]),
        threshold=float(status["threshold"]),
        ood=bool(status["decision"]),
        released=bool(status["released"]),
        new_prediction=bool(status["new_prediction"]),
        controller=controller,
        perturbed=False,
        needle_in_tissue=False,
        consulted=consulted,
    )


def _add_env_record(log: StepLog, info: dict) -> None:
    """What the env said of the step."""
    log.perturbed = bool(info["perturbed"])
    log.needle_in_tissue = bool(info["needle_in_tissue"])
    log.h = float(info.get("h", math.nan))
    log.cbf_active = bool(info.get("cbf_active", False))
    log.cbf_intervened = bool(info.get("cbf_intervened", False))
    log.throw_index = int(info.get("throw_index", 0))
