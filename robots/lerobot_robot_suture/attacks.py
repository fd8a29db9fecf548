"""Adversarial episodes against the ``suture_cbf`` step on the robot path, the barrier read at the physics rate.

The same attack families as the env-path benchmark (``lerobot_suture.experiments.cbf_attacks``), sent the way
``lerobot-rollout`` sends a policy's actions: robot observation -> robot action pipeline (``suture_cbf``) ->
``SutureSim.send_action``. The arm runs ``tip_tracking`` and reports its registration; the step sees only the
robot's observation, through the robot's faults when asked (``--robot.faults.*``: observation and command
latency, an arm that lags).
The needle tip is read after every physics step against the wound where it really is; a violation is a physics
step at which the needle, held by the simulator's grasp, has its tip in the tissue outside the wound's ellipsoid,
counted at every step of the episode whatever the step says of its own state
(:meth:`~lerobot_suture.experiments.cbf_attacks.AttackEpisode.record_harm`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from lerobot.processor import RobotProcessorPipeline
from lerobot.processor.converters import robot_action_observation_to_transition, transition_to_robot_action

from lerobot_suture.experiments.cbf_attacks import (
    FAMILIES,
    AttackEpisode,
    Attacker,
    lead_in_steps,
    wound_in_phantom_frame,
)
from lerobot_suture.expert import ScriptedExpert
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.safety.tip_guard import PHASE_ACTIVE, PHASE_DONE

from .cbf_step import SutureCBFStep
from .config_suture_sim import POSE_FEATURES, SutureSimConfig
from .faults import FaultConfig
from .suture_sim import SutureSim


@dataclass
class RobotAttackEpisode(AttackEpisode):
    """One attacked episode on the robot path: an :class:`AttackEpisode` (``active_steps`` and
    ``interventions`` count the control steps whose action the step filtered) with the robot's fault settings
    that are on."""

    faults: dict = field(default_factory=dict)


def make_robot_path(
    cbf: CBFConfig | None = None,
    image_size: int = 64,
    faults: FaultConfig | None = None,
    task: str = "insertion",
):
    """A connected ``SutureSim`` (fast clock, tip tracking, registration, physics-rate tip trace, ``faults``,
    ``task``), the robot action pipeline holding ``suture_cbf`` (its declared latency that of ``faults``), and
    the step."""
    faults = faults or FaultConfig()
    config = SutureSimConfig(
        task=task,
        faults=faults,
        image_size=image_size,
        clock="fast",
        episode_end="hold",
        tip_tracking=True,
        registration=True,
        tip_trace=True,
    )
    robot = SutureSim(config)
    robot.connect()
    latency = faults.observation_latency + faults.command_latency
    step = SutureCBFStep(cbf=cbf or CBFConfig(enabled=True), latency_steps=latency)
    pipeline = RobotProcessorPipeline(
        steps=[step],
        to_transition=robot_action_observation_to_transition,
        to_output=transition_to_robot_action,
        name="robot_action_processor",
    )
    return robot, pipeline, step


def _send(robot, pipeline, step, action: np.ndarray, episode: RobotAttackEpisode, cbf: CBFConfig) -> bool:
    """One control step through the pipeline; returns whether the scene's episode is over."""
    observation = robot.get_observation()
    command = dict(zip(POSE_FEATURES, np.asarray(action, dtype=float).tolist(), strict=True))
    robot.send_action(pipeline((command, observation)))
    result = step.last_result
    info = robot.last_info
    # Harm is read from the simulator, for the measurement only: the step never sees it.
    if info["needle_grasped"]:
        trace = np.asarray(info["needle_tip_trace_phantom"])
        episode.record_harm(trace, wound_in_phantom_frame(robot.env.unwrapped), cbf.semi_axes)
    else:
        episode.released = True
    if result is not None and result.guarding:
        episode.active_steps += 1
        episode.interventions += int(result.intervened)
    return robot.scene_over


def run_robot_attack_episode(
    robot_path,
    family: str,
    seed: int,
    attack_steps: int = 30,
    max_start_delay: int = 8,
    max_steps: int = 100,
    throw: int = 0,
) -> RobotAttackEpisode:
    """One episode of ``family`` from ``seed`` on a robot path from :func:`make_robot_path`.

    The expert leads in through the pipeline until throw ``throw`` (a running suture's; the expert sutures the
    ones before it) has been under way for ``0..max_start_delay`` control steps (drawn from the seed), then the
    attacker commands the arm for up to ``attack_steps``. ``max_steps`` is as in
    :func:`~lerobot_suture.experiments.cbf_attacks.run_attack_episode`.
    """
    robot, pipeline, step = robot_path
    cbf = step.cbf
    rng = np.random.default_rng([seed, FAMILIES.index(family), throw])
    attacker = Attacker(family, rng)
    defaults = asdict(FaultConfig())
    faults = {k: v for k, v in asdict(robot.config.faults).items() if v != defaults[k]}
    episode = RobotAttackEpisode(family=family, seed=seed, throw=throw, faults=faults)
    robot.reset_scene(seed)
    pipeline.reset()
    expert = ScriptedExpert()
    expert.reset(robot.env)
    limit = lead_in_steps(robot.config.task, throw, max_steps)
    start_delay, delay, steps = int(rng.integers(max_start_delay + 1)), 0, 0
    while steps < limit:
        # The throw as the step has seen it registered (under observation latency, later than the scene).
        if step.throw_index == throw and step.phase == PHASE_ACTIVE:
            if delay >= start_delay:
                break
            delay += 1
        over = _send(robot, pipeline, step, expert.act(robot.env), episode, cbf)
        steps += 1
        seen = step.throw_index or 0
        if over or seen > throw or (seen == throw and step.phase == PHASE_DONE):
            return episode
    else:
        return episode
    attacker.begin(robot.env)
    for k in range(min(attack_steps, limit - steps)):
        episode.attack_steps += 1
        if _send(robot, pipeline, step, attacker.act(robot.env, k), episode, cbf):
            break
    return episode
