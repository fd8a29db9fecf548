"""Adversarial episodes against the ``suture_cbf`` step on the robot path, the barrier read at the physics rate.

The same attack families as the env-path benchmark (``lerobot_suture.experiments.cbf_attacks``), sent the way
``lerobot-rollout`` sends a policy's actions: robot observation -> robot action pipeline (``suture_cbf``) ->
``SutureSim.send_action``. The arm runs ``tip_tracking`` and reports its registration; the step sees only the
robot's observation, through the robot's faults when asked (``--robot.faults.*``: observation and command
latency, an arm that lags).
h is read from the needle tip after every physics step against the wound where it really is; a violation is a
physics step with h < 0 during a control step whose action the step filtered, before the jaw let the needle go.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
from lerobot.processor import RobotProcessorPipeline
from lerobot.processor.converters import robot_action_observation_to_transition, transition_to_robot_action

from lerobot_suture.experiments.cbf_attacks import FAMILIES, Attacker
from lerobot_suture.expert import ScriptedExpert
from lerobot_suture.safety.cbf import ellipsoid_h
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.safety.tip_guard import PHASE_ACTIVE, PHASE_IDLE, Wound

from .cbf_step import SutureCBFStep
from .config_suture_sim import POSE_FEATURES, SutureSimConfig
from .faults import FaultConfig
from .suture_sim import SutureSim


@dataclass
class RobotAttackEpisode:
    """One attacked episode on the robot path.

    Attributes:
        family, seed: what was run. faults: the robot's fault settings that are on.
        active_steps: control steps whose action the step filtered (lead-in included).
        attack_steps: control steps the attacker commanded.
        violation_steps: physics steps with h < 0 during active control steps.
        h_min: smallest h over those physics steps (nan if never active).
        interventions: active control steps in which the step changed the command.
        released: the jaw has let the needle go (no step after it counts).
    """

    family: str
    seed: int
    faults: dict = field(default_factory=dict)
    active_steps: int = 0
    attack_steps: int = 0
    violation_steps: int = 0
    h_min: float = math.nan
    interventions: int = 0
    released: bool = False


def make_robot_path(cbf: CBFConfig | None = None, image_size: int = 64, faults: FaultConfig | None = None):
    """A connected ``SutureSim`` (fast clock, tip tracking, registration, physics-rate tip trace, ``faults``),
    the robot action pipeline holding ``suture_cbf``, and the step."""
    config = SutureSimConfig(
        faults=faults or FaultConfig(),
        image_size=image_size,
        clock="fast",
        episode_end="hold",
        tip_tracking=True,
        registration=True,
        tip_trace=True,
    )
    robot = SutureSim(config)
    robot.connect()
    step = SutureCBFStep(cbf=cbf or CBFConfig(enabled=True))
    pipeline = RobotProcessorPipeline(
        steps=[step],
        to_transition=robot_action_observation_to_transition,
        to_output=transition_to_robot_action,
        name="robot_action_processor",
    )
    return robot, pipeline, step


def _true_h(robot: SutureSim, cbf: CBFConfig) -> np.ndarray:
    base = robot.env.unwrapped
    wound = Wound(base.entry_point, base.exit_point, base.phantom_rotation[:, 2])
    center, rotation = wound.ellipsoid_frame()
    return np.asarray(ellipsoid_h(robot.last_info["needle_tip_trace"], center, cbf.semi_axes, rotation))


def _send(robot, pipeline, step, action: np.ndarray, episode: RobotAttackEpisode, cbf: CBFConfig) -> bool:
    """One control step through the pipeline; returns whether the scene's episode is over."""
    observation = robot.get_observation()
    command = dict(zip(POSE_FEATURES, np.asarray(action, dtype=float).tolist(), strict=True))
    robot.send_action(pipeline((command, observation)))
    result = step.last_result
    # The guarantee ends when the jaw lets the needle go, as on the env path: a released needle falls freely,
    # and one the jaw catches again sits in a new grasp. Under observation latency the step learns of the
    # release late, so the release is read from the simulator here, for the measurement only.
    if not robot.last_info["needle_grasped"]:
        episode.released = True
    if result is not None and result.active and not episode.released:
        h = _true_h(robot, cbf)
        episode.active_steps += 1
        episode.violation_steps += int(np.sum(h < 0.0))
        low = float(np.min(h))
        episode.h_min = low if math.isnan(episode.h_min) else min(episode.h_min, low)
        episode.interventions += int(result.intervened)
    return robot.scene_over


def run_robot_attack_episode(
    robot_path,
    family: str,
    seed: int,
    attack_steps: int = 30,
    max_start_delay: int = 8,
    max_steps: int = 100,
) -> RobotAttackEpisode:
    """One episode of ``family`` from ``seed`` on a robot path from :func:`make_robot_path`.

    The expert leads in through the pipeline until the step has been active ``0..max_start_delay`` control
    steps (drawn from the seed), then the attacker commands the arm for up to ``attack_steps``.
    """
    robot, pipeline, step = robot_path
    cbf = step.cbf
    rng = np.random.default_rng([seed, FAMILIES.index(family)])
    attacker = Attacker(family, rng)
    defaults = asdict(FaultConfig())
    faults = {k: v for k, v in asdict(robot.config.faults).items() if v != defaults[k]}
    episode = RobotAttackEpisode(family=family, seed=seed, faults=faults)
    robot.reset_scene(seed)
    pipeline.reset()
    expert = ScriptedExpert()
    expert.reset(robot.env)
    start_delay, delay, steps = int(rng.integers(max_start_delay + 1)), 0, 0
    while steps < max_steps:
        if step.phase == PHASE_ACTIVE:
            if delay >= start_delay:
                break
            delay += 1
        over = _send(robot, pipeline, step, expert.act(robot.env), episode, cbf)
        steps += 1
        if over or step.phase not in (PHASE_IDLE, PHASE_ACTIVE):
            return episode
    else:
        return episode
    attacker.begin(robot.env)
    for k in range(min(attack_steps, max_steps - steps)):
        episode.attack_steps += 1
        if _send(robot, pipeline, step, attacker.act(robot.env, k), episode, cbf):
            break
    return episode
