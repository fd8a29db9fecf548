"""One policy episode with a surgeon in the loop: the gate, the takeover, recording and the live view.

Each control step: the surgeon is polled (take over, hand back); while the policy is in control it acts
and its gate reports (an enforced gate that releases control hands it to the surgeon, or to a hold of
the released pose when nobody is there), and a scripted surgeon may take over on seeing the action,
before it runs; the :class:`~lerobot_suture.surgeon.takeover.Takeover` names the
step's actor; the env steps. Whatever reaches the robot goes through the env's step, so a CBF wrapper
filters the surgeon's commands as the policy's. The policy is not asked while it is out of control
(its score is then NaN, its decision "not consulted"); a hand-back resets it, re-arming its gate.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from lerobot_suture.surgeon.record_run import NOT_CONSULTED
from lerobot_suture.surgeon.takeover import Actor, Takeover


@dataclass
class SurgeonStep:
    actor: Actor
    score: float
    threshold: float
    decision: int  # 1 O.O.D., 0 in distribution, -1 not consulted
    released: bool
    cbf_intervened: bool


@dataclass
class SurgeonEpisode:
    seed: int
    success: bool = False
    steps: list[SurgeonStep] = field(default_factory=list)
    handovers: list[tuple[int, Actor, Actor, str]] = field(default_factory=list)
    stop_reason: str = ""

    @property
    def actors(self) -> list[Actor]:
        return [s.actor for s in self.steps]


def run_surgeon_episode(
    env, runner, surgeon, seed: int, max_steps: int, recorder=None, view=None, script=None
):
    """One episode of ``runner`` (a ``PolicyRunner``) in ``env`` with ``surgeon`` (``surgeons.py``).

    Args:
        recorder: a :class:`~lerobot_suture.surgeon.record_run.RunRecorder`, or None.
        view: a :class:`~lerobot_suture.surgeon.live_view.LiveView`, or None.
        script: a scripted input source (``before_poll(step)``, ``after_poll(step)``) driving the
            surgeon's teleoperator, or None.

    Returns:
        :class:`SurgeonEpisode`. LeRobot's teleop events end the episode early: ``success`` / ``q`` stop
        it, and the recorder then keeps it (a re-record request discards it).
    """
    from lerobot.teleoperators.utils import TeleopEvents

    torch.manual_seed(int(seed))
    observation, info = env.reset(seed=int(seed))
    runner.reset()
    surgeon.begin_episode(env)
    takeover = Takeover(has_surgeon=surgeon.present)
    log = SurgeonEpisode(seed=int(seed))
    held = None  # the hold action once the gate released control with nobody to take over
    rerecord = False
    for step in range(max_steps):
        if script is not None:
            script.before_poll(step)
        command = surgeon.poll()
        if script is not None:
            script.after_poll(step)
        before = takeover.actor
        status = {"score": math.nan, "threshold": math.nan, "decision": NOT_CONSULTED, "released": False}
        action = None
        if before is Actor.POLICY and not (command.take_over and surgeon.present):
            action, status = _policy_step(runner, observation)
            if surgeon.intervenes(env, action):
                command = dataclasses.replace(command, take_over=True)
        actor = takeover.update(
            step, released=status["released"], take_over=command.take_over, hand_back=command.hand_back
        )
        if actor is Actor.POLICY and before is not Actor.POLICY:
            runner.reset()  # the hand-back re-arms the gate: a fresh start from this observation
            action, status = _policy_step(runner, observation)
        elif actor is Actor.SURGEON:
            if before is not Actor.SURGEON:
                surgeon.take_control(env, observation)
            action = surgeon.act(env, command)
        elif actor is Actor.HOLD:
            held = action if before is not Actor.HOLD else held  # the policy's hold action at the release
            action = held
        if recorder is not None:
            recorder.observe(env)
        if view is not None:
            view.log(step, observation, status["score"], status["threshold"], actor)
        next_observation, reward, terminated, truncated, info = env.step(action)
        done = bool(terminated or truncated)
        if recorder is not None:
            recorder.add(
                env, observation, action, reward, info, done, actor, status["score"], status["decision"]
            )
        log.steps.append(
            SurgeonStep(
                actor,
                float(status["score"]),
                float(status["threshold"]),
                int(status["decision"]),
                bool(status["released"]),
                bool(info.get("cbf_intervened", False)),
            )
        )
        observation = next_observation
        events = command.events
        rerecord = bool(events.get(TeleopEvents.RERECORD_EPISODE, False))
        if done or rerecord or events.get(TeleopEvents.TERMINATE_EPISODE) or events.get(TeleopEvents.SUCCESS):
            log.stop_reason = "env" if done else "rerecord" if rerecord else "teleop event"
            break
    else:
        log.stop_reason = "max_steps"
    log.success = bool(info["is_success"])
    log.handovers = list(takeover.handovers)
    if recorder is not None:
        if rerecord:
            recorder.dataset.clear_episode_buffer()
        else:
            recorder.save_episode()
    return log


def _policy_step(runner, observation) -> tuple[np.ndarray, dict]:
    """The policy's action and its gate's status (a policy without a gate reports nothing)."""
    action = runner.act(observation)
    ood_status = getattr(runner.policy, "ood_status", None)
    if ood_status is None:
        return action, {
            "score": math.nan,
            "threshold": math.nan,
            "decision": NOT_CONSULTED,
            "released": False,
        }
    status = ood_status(0)
    return action, {
        "score": status["score"],
        "threshold": status["threshold"],
        "decision": int(bool(status["decision"])) if math.isfinite(status["score"]) else NOT_CONSULTED,
        "released": bool(status["released"]),
    }
