"""One policy episode with a surgeon in the loop: the env path's episode loop
(:func:`~lerobot_suture.runtime.rollout.rollout_episodes`) with a person's teleoperator, a recording of the run and
the live view as its hooks.

The loop polls the surgeon every control step (take over, hand back); the policy acts while it is in control,
its gate may release control, and a hand-back resets the policy, re-arming its gate. The policy is not asked
while it is out of control: its score is then NaN, and the recording marks its decision "not consulted".
"""

from __future__ import annotations

import math

from lerobot_suture.runtime.rollout import EpisodeHooks, EpisodeLog, StepLog, rollout_episodes
from lerobot_suture.runtime.takeover import Actor
from lerobot_suture.surgeon.record_run import NOT_CONSULTED


def gate_decision(log: StepLog) -> int:
    """The recording's gate decision of a step: 1 O.O.D., 0 in distribution, -1 not consulted (the policy was not
    asked, or it has no gate)."""
    return int(log.ood) if log.consulted and math.isfinite(log.score) else NOT_CONSULTED


class SessionHooks(EpisodeHooks):
    """A recorder, a live view and a scripted input source, each optional, on one env's episode."""

    def __init__(self, recorder=None, view=None, script=None):
        self.recorder, self.view, self.script = recorder, view, script

    def before_poll(self, row: int, step: int) -> None:
        if self.script is not None:
            self.script.before_poll(step)

    def after_poll(self, row: int, step: int) -> None:
        if self.script is not None:
            self.script.after_poll(step)

    def before_step(self, row: int, step: int, env, observation: dict, actor: Actor, log: StepLog) -> None:
        if self.recorder is not None:
            self.recorder.observe(env)
        if self.view is not None:
            self.view.log(step, observation, log.score, log.threshold, actor)

    def after_step(
        self, row: int, env, observation: dict, action, reward, info: dict, done: bool, log: StepLog
    ) -> None:
        if self.recorder is not None:
            self.recorder.add(
                env, observation, action, reward, info, done, log.actor, log.score, gate_decision(log)
            )

    def end_episode(self, row: int, log: EpisodeLog, rerecord: bool) -> None:
        if self.recorder is None:
            return
        if rerecord:
            self.recorder.dataset.clear_episode_buffer()
        else:
            self.recorder.save_episode()


def run_surgeon_episode(
    env, runner, surgeon, seed: int, max_steps: int, recorder=None, view=None, script=None
) -> EpisodeLog:
    """One episode of ``runner`` (a ``PolicyRunner``) in ``env`` with ``surgeon`` (``surgeons.py``).

    Args:
        recorder: a :class:`~lerobot_suture.surgeon.record_run.RunRecorder`, or None.
        view: a :class:`~lerobot_suture.surgeon.live_view.LiveView`, or None.
        script: a scripted input source (``before_poll(step)``, ``after_poll(step)``) driving the
            surgeon's teleoperator, or None.

    Returns:
        The episode's log. LeRobot's teleop events end the episode early: ``success`` / ``q`` stop it, and the
        recorder then keeps it (a re-record request discards it).
    """
    hooks = SessionHooks(recorder, view, script)
    return rollout_episodes([env], runner, [seed], [surgeon], max_steps, hooks=hooks)[0]
