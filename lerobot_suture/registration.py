"""Gymnasium registration, from the task table, and the factory it points to."""

from __future__ import annotations

import gymnasium as gym

from lerobot_suture.sim.tasks import DEFAULT_TASK, TASKS

ENV_ID = TASKS[DEFAULT_TASK].gym_id
"""The default task's id, ``lerobot_suture/NeedleInsertion-v0``."""
MAX_EPISODE_STEPS = TASKS[DEFAULT_TASK].max_episode_steps
"""10 s at the 10 Hz control rate; the expert needs about 6 s."""

_ENTRY_POINT = "lerobot_suture.registration:make_suture_env"


def make_suture_env(
    cbf=None,
    id_task: str | None = None,
    marks: bool = False,
    subtask: bool = False,
    regrasp_target: bool = False,
    regrasp_from: str = "marks",
    relative_actions: bool = False,
    arc_guard: bool = False,
    **kwargs,
) -> gym.Env:
    """A :class:`~lerobot_suture.sim.suture_env.SutureEnv`, behind the CBF safety filter when asked.

    Args:
        cbf: None (no filter), or a :class:`~lerobot_suture.safety.cbf_config.CBFConfig` (or its fields
            as a dict); the env is then wrapped in
            :class:`~lerobot_suture.safety.cbf_wrapper.CBFActionWrapper`.
        id_task: the task of the Gymnasium id that made the env (its registration passes it): the id's
            ``max_episode_steps`` is that task's.
        marks: add the current throw's entry and exit marks to the observation as ``environment_state``
            (:class:`~lerobot_suture.sim.wound_marks.WoundMarks`).
        subtask: add the high level's subtask and throw to ``environment_state``, after the marks
            (:class:`~lerobot_suture.sim.subtasks.SubtaskObservation`).
        regrasp_target: add the regrasp planned through the marks, in the jaw frame, to ``environment_state``,
            after the marks and the subtask (:class:`~lerobot_suture.sim.regrasp_target.RegraspTarget`).
        regrasp_from: where that plan comes from: ``"marks"`` (the arc through them) or ``"release"`` (the needle
            where the jaw let go of it at the end of the insert); only with ``regrasp_target``.
        relative_actions: take actions relative to the jaw's measured pose, in the jaw frame
            (:class:`~lerobot_suture.sim.relative_actions.RelativeActions`).
        arc_guard: while the needle is held in tissue, let it only turn about its own centre
            (:class:`~lerobot_suture.safety.arc_guard.NeedleArcGuard`).
        **kwargs: the env's own arguments (see its docstring), ``task`` among them.

    Raises:
        ValueError: ``task`` is not the id's task: Gymnasium would cut its episodes at the id's length; or
            ``regrasp_from`` is none of its sources, or given without ``regrasp_target``.
    """
    from lerobot_suture.sim.suture_env import SutureEnv

    task = kwargs.get("task", id_task)
    if id_task is not None and task != id_task and task in TASKS:
        made, wanted = TASKS[id_task], TASKS[task]
        raise ValueError(
            f"gym.make('{made.gym_id}', task={task!r}) would cut every {task} episode at {made.gym_id}'s "
            f"{made.max_episode_steps} steps. Make the task's own id instead: gym.make('{wanted.gym_id}') "
            f"({wanted.max_episode_steps} steps; max_episode_steps=N changes it)."
        )

    from lerobot_suture.sim.regrasp_target import check_regrasp_source

    check_regrasp_source(regrasp_from, regrasp_target, "regrasp_target=True")
    env = SutureEnv(**kwargs)
    if arc_guard:
        from lerobot_suture.safety.arc_guard import NeedleArcGuard

        env = NeedleArcGuard(env)
    if relative_actions:
        from lerobot_suture.sim.relative_actions import RelativeActions

        env = RelativeActions(env)
    if marks:
        from lerobot_suture.sim.wound_marks import WoundMarks

        env = WoundMarks(env)
    if subtask:
        from lerobot_suture.sim.subtasks import SubtaskObservation

        env = SubtaskObservation(env)
    if regrasp_target:
        from lerobot_suture.sim.regrasp_target import RegraspTarget

        env = RegraspTarget(env, regrasp_from)
    if cbf is None:
        return env
    from lerobot_suture.safety.cbf_config import CBFConfig
    from lerobot_suture.safety.cbf_wrapper import CBFActionWrapper

    if isinstance(cbf, dict):
        cbf = CBFConfig(**cbf)
    if not isinstance(cbf, CBFConfig):
        raise ValueError(
            f"`cbf` must be a CBFConfig, a dict of its fields, or None. Got {type(cbf).__name__}."
        )
    return CBFActionWrapper(env, cbf)


def register_envs() -> None:
    """Register one id per task (``tasks.TASKS``): its ``task`` and its episode length."""
    for spec in TASKS.values():
        if spec.gym_id not in gym.registry:
            gym.register(
                id=spec.gym_id,
                entry_point=_ENTRY_POINT,
                max_episode_steps=spec.max_episode_steps,
                kwargs={"task": spec.name, "id_task": spec.name},
            )
