"""The robot path for the attack episodes of ``lerobot_suture.experiments.attack_episodes``.

:class:`RobotPath` sends each action the way ``lerobot-rollout`` sends a policy's: robot observation -> the robot
action pipeline holding ``suture_cbf`` -> ``SutureSim.send_action``. The arm runs its tip-tracking controller and
reports its registration; the step sees only the robot's observation, through the robot's faults when the
condition has them (observation and command latency, an arm that lags), and declares the latency they add.
Harm is read from the simulator by the episode loop, for the measurement only: the step never sees it.
"""

from __future__ import annotations

import numpy as np
from lerobot.processor import RobotProcessorPipeline
from lerobot.processor.converters import robot_action_observation_to_transition, transition_to_robot_action

from lerobot_suture.experiments.attack_episodes import AttackCondition, PathStep
from lerobot_suture.safety.cbf_config import CBFConfig

from .cbf_step import SutureCBFStep
from .config_suture_sim import CAMERA, POSE_FEATURES, SutureSimConfig
from .faults import FaultConfig
from .suture_sim import SutureSim


class RobotPath:
    """A connected ``SutureSim`` (fast clock, tip tracking, registration, physics-rate tip trace) in
    ``condition``, and the robot action pipeline holding ``suture_cbf``.

    Args:
        condition: the scene and the arm's faults. cbf: the filter (None: ``CBFConfig(enabled=True)``).
        image_size: the endoscope image side (px): small for the attacks, which do not read it; a policy's
            own for a policy acting from :attr:`observation`.
    """

    def __init__(self, condition: AttackCondition, cbf: CBFConfig | None = None, image_size: int = 32):
        faults = FaultConfig(**condition.faults)
        config = SutureSimConfig(
            task=condition.task,
            scenario=condition.scenario,
            scenario_magnitude=condition.scenario_magnitude,
            faults=faults,
            image_size=image_size,
            clock="fast",
            episode_end="hold",
            tip_tracking=True,
            registration=True,
            tip_trace=True,
        )
        self.robot = SutureSim(config)
        self.robot.connect()
        latency = faults.observation_latency + faults.command_latency
        self.step = SutureCBFStep(cbf=cbf or CBFConfig(enabled=True), latency_steps=latency)
        self.pipeline = RobotProcessorPipeline(
            steps=[self.step],
            to_transition=robot_action_observation_to_transition,
            to_output=transition_to_robot_action,
            name="robot_action_processor",
        )
        self.task = condition.task
        self.semi_axes = self.step.cbf.semi_axes

    @property
    def scene(self):
        return self.robot.env

    @property
    def observation(self) -> dict:
        """What a policy acting on the arm sees, in the env's layout (``pixels``, ``agent_pos``): the robot's
        observation, through its faults, as ``lerobot-rollout`` hands it to a policy."""
        observation = self.robot.get_observation()
        pose = np.array([observation[name] for name in POSE_FEATURES], dtype=np.float32)
        return {"pixels": {CAMERA: observation[CAMERA]}, "agent_pos": pose}

    @property
    def phase(self) -> str:
        return self.step.phase

    @property
    def throw_index(self) -> int | None:
        return self.step.throw_index

    def reset(self, seed: int) -> None:
        self.robot.reset_scene(seed)
        self.pipeline.reset()

    def send(self, action: np.ndarray) -> PathStep:
        observation = self.robot.get_observation()
        command = dict(zip(POSE_FEATURES, np.asarray(action, dtype=float).tolist(), strict=True))
        self.robot.send_action(self.pipeline((command, observation)))
        result = self.step.last_result
        guarding = result is not None and result.guarding
        return PathStep(
            self.robot.scene_over,
            self.robot.last_info,
            guarding,
            guarding and result.intervened,
            result is not None and result.motion_exceeded,
        )

    def close(self) -> None:
        self.robot.disconnect()
