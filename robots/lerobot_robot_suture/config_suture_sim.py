"""``SutureSimConfig``: the simulated suturing arm as LeRobot's robot type ``suture_sim``."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from lerobot.robots.config import RobotConfig

from lerobot_suture.datasets.features import POSE_NAMES
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.sim.appearance import AppearanceConfig
from lerobot_suture.sim.regrasp_target import REGRASP_TARGET_NAMES, check_regrasp_source
from lerobot_suture.sim.scenarios import SAFETY_SCENARIOS, SCENARIOS
from lerobot_suture.sim.suture_env import check_image_side
from lerobot_suture.sim.task import GRASP_RANGES
from lerobot_suture.sim.tasks import check_scenario, task_spec
from lerobot_suture.sim.wound_marks import MARKS_NAMES

from .faults import FaultConfig

CAMERA = "endoscope"
"""The camera's name: LeRobot stores it as ``observation.images.endoscope``, the expert data's key."""
WRIST_CAMERA = "wrist"
"""The wrist camera's name (``--robot.wrist_camera=true``): ``observation.images.wrist``."""
POSE_FEATURES = [f"{name}.pos" for name in POSE_NAMES]
"""The pose's scalar feature names, in the expert data's order (x, y, z, r11, r21, r31, r12, r22, r32,
jaw). LeRobot stacks them into ``observation.state`` (10,) and ``action`` (10,); the ``.pos`` suffix is
LeRobot's for a position feature, and ``lerobot-rollout`` keeps only scalar features named ``*.pos`` or
``*.vel`` (``lerobot/rollout/context.py``)."""
MARK_FEATURES = [f"{name}.pos" for name in MARKS_NAMES]
"""The wound's marks as scalar features (``--robot.marks=true``; entry x, y, z, exit x, y, z, m, the arm's base
frame). Named ``*.pos`` so that LeRobot routes them to the policy: ``lerobot-rollout`` and ``lerobot-record`` stack
them into ``observation.state`` after the pose, (16,), which the ``suture_chain`` policy splits again."""
REGRASP_TARGET_FEATURES = [f"{name}.pos" for name in REGRASP_TARGET_NAMES]
"""The planned regrasp as scalar features (``--robot.regrasp_target=true``; the motion to it in the jaw frame, m,
then the rotation change's first two columns), after the marks in ``observation.state``: (25,) with the marks."""
CLOCKS = ("realtime", "fast")
EPISODE_ENDS = ("continue", "hold")


@RobotConfig.register_subclass("suture_sim")
@dataclass
class SutureSimConfig(RobotConfig):
    """The suturing scene (arm, needle, phantom, endoscope) of ``lerobot_suture.sim.suture_env``.

    Args:
        task: the task the scene is set for (``lerobot_suture.sim.tasks.TASKS``): ``insertion`` (the needle
            starts in the jaw), ``pickup`` (it lies on the phantom, the jaw open) ``extraction`` (it starts
            driven through the tissue) or ``running_suture`` (four throws along the wound).
        seed: seed of the scene at ``connect``; LeRobot's dataset episode ``N`` (``lerobot-record``,
            ``lerobot-rollout --strategy.type=episodic``) plays the scene of ``seed + N``.
        image_size: endoscope image side (px).
        wrist_camera: add the image of a camera on the instrument's shaft (``wrist``, ``image_size`` too), as
            a surgical robot with a wrist camera on each instrument reports it.
        marks: report the current throw's entry and exit marks (:data:`MARK_FEATURES`), as a registered wound
            gives them (the env's ``marks=True``): the policy's input, where ``registration`` is the CBF's.
        regrasp_target: report the regrasp planned through the current throw's marks, seen from the measured
            pose in the jaw frame (:data:`REGRASP_TARGET_FEATURES`; the env's ``regrasp_target=True``), as a
            system with the registered wound and the needle's geometry plans it: the policy's input.
        regrasp_from: where that plan comes from: ``marks`` (the arc through them) or ``release`` (the needle
            where the jaw let go of it at the end of the insert; the env's ``regrasp_from``).
        arc_guard: while the needle is held in tissue, let it only turn about its own centre
            (``lerobot_suture.safety.arc_guard``; the env's ``arc_guard=True``).
        scenario: perturbation scenario, one of ``lerobot_suture.sim.scenarios.SCENARIOS`` (or, in a task with a
            throw, ``SAFETY_SCENARIOS``: tissue that breathes).
        scenario_onset_step: onset (control steps); None takes the scenario's default.
        scenario_magnitude: magnitude (rad or m); None takes the scenario's default.
        grasp: grasp randomization, ``narrow`` or ``wide`` (``task.GRASP_RANGES``).
        appearance: per-scene appearance randomization of the endoscope's view, every option off by
            default (``--robot.appearance.haze=0.3``; ranges in ``lerobot_suture.sim.appearance``).
        cbf: the control barrier function safety filter (``--robot.cbf.enabled=true``).
        clock: ``realtime`` (a control step takes at least the control period, 0.1 s, of wall time, as
            a real arm runs) or ``fast`` (a control step takes the time it computes in).
        episode_end: what the arm does once the scene's episode has ended (the throw is over, or the env's
            10 s limit came): ``continue`` (it keeps following the commands in the finished scene: a person
            at the controls) or ``hold`` (it holds its last pose until the next scene, as ``lerobot-eval``
            stops an env at its episode's end: evaluation).
        tip_tracking: while the needle is held, the arm's controller drives its tip in a straight line to where
            the target pose puts it (tip-first; ``SutureEnv(tip_tracking=True)``): the controller the robot path's
            ``suture_cbf`` processor step relies on. Off: the env's pose controller, as ``lerobot-eval`` runs it.
        registration: report the registered wound (``entry_point.*``, ``exit_point.*``, ``surface_normal.*``,
            ``throw.index``; tasks with a throw) and the needle in the jaw (``needle_grasp.*``) as observation
            features, as a registration and a needle tracker would: what ``suture_cbf`` reads. ``lerobot-rollout``
            keeps them out of the policy's state and the dataset (only ``*.pos`` scalars go there); leave it off
            for ``lerobot-record``, which would stack them into ``observation.state``.
        faults: faults a real arm has, injected on this robot's I/O (``faults.FaultConfig``; all off by default):
            a frozen or dropping endoscope, observation and command latency (control steps), an arm that lags.
        tip_trace: record the needle tip after every physics step (``last_info["needle_tip_trace"]``), to read
            the barrier at the physics rate (benchmarks; slower).
        trace_path: append one JSON line per executed control step to this file: the scene's seed, the
            step, the needle tip (m), the measured pose, the env's outcome and the step's wall time (s).
            None: no trace.
    """

    task: str = "insertion"
    seed: int = 0
    image_size: int = 96
    wrist_camera: bool = False
    marks: bool = False
    regrasp_target: bool = False
    regrasp_from: str = "marks"
    arc_guard: bool = False
    scenario: str = "nominal"
    scenario_onset_step: int | None = None
    scenario_magnitude: float | None = None
    grasp: str = "narrow"
    appearance: AppearanceConfig = field(default_factory=AppearanceConfig)
    cbf: CBFConfig = field(default_factory=CBFConfig)
    clock: str = "realtime"
    episode_end: str = "continue"
    tip_tracking: bool = False
    registration: bool = False
    faults: FaultConfig = field(default_factory=FaultConfig)
    tip_trace: bool = False
    trace_path: Path | None = None

    def __post_init__(self):
        super().__post_init__()
        if self.scenario not in SCENARIOS + SAFETY_SCENARIOS:
            raise ValueError(
                f"`scenario` must be one of {SCENARIOS + SAFETY_SCENARIOS}. Got {self.scenario!r}."
            )
        check_scenario(self.task, self.scenario)
        if self.grasp not in GRASP_RANGES:
            raise ValueError(f"`grasp` must be one of {tuple(GRASP_RANGES)}. Got {self.grasp!r}.")
        if self.clock not in CLOCKS:
            raise ValueError(f"`clock` must be one of {CLOCKS}. Got {self.clock!r}.")
        if self.episode_end not in EPISODE_ENDS:
            raise ValueError(f"`episode_end` must be one of {EPISODE_ENDS}. Got {self.episode_end!r}.")
        if self.seed < 0:
            raise ValueError(f"`seed` must be >= 0. Got {self.seed}.")
        check_image_side("image_size", self.image_size)
        check_regrasp_source(self.regrasp_from, self.regrasp_target, "--robot.regrasp_target=true")

    @property
    def gym_id(self) -> str:
        """The task's Gymnasium id."""
        return task_spec(self.task).gym_id

    def env_kwargs(self) -> dict:
        """Arguments of ``gym.make(self.gym_id, ...)`` for this scene."""
        return {
            "obs_type": "pixels_agent_pos",
            "image_size": self.image_size,
            "render_mode": None,
            "scenario": self.scenario,
            "scenario_onset_step": self.scenario_onset_step,
            "scenario_magnitude": self.scenario_magnitude,
            "grasp": self.grasp,
            "appearance": self.appearance,
            "cbf": self.cbf if self.cbf.enabled else None,
            "tip_tracking": self.tip_tracking,
            "record_tip_trace": self.tip_trace,
            **({"wrist_camera": True} if self.wrist_camera else {}),
            **({"marks": True} if self.marks else {}),
            **({"regrasp_target": True} if self.regrasp_target else {}),
            **({"regrasp_from": self.regrasp_from} if self.regrasp_from != "marks" else {}),
            **({"arc_guard": True} if self.arc_guard else {}),
        }
