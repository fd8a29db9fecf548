"""``suture_cbf``: the CBF as a robot-action processor step, between a policy (or a teleoperator) and the arm.

Registered in LeRobot's ``ProcessorStepRegistry`` when the plugin is imported, so a saved
``RobotProcessorPipeline`` names it, and placed by this plugin's rollout strategies in the robot action
pipeline that ``lerobot-rollout`` runs before ``send_action`` (``docs/safety.md``). It filters each commanded
motion of the needle tip with :class:`~lerobot_suture.safety.tip_guard.TipGuard` from what a real system has:

- the measured pose of the needle holder (the observation's ``x.pos`` ... ``jaw.pos``: kinematics);
- the grasp model: where the needle sits in the jaw, from the observation's ``needle_grasp.*`` features when
  the arm reports them (a needle tracker), else from ``grasp`` in the config;
- the registered wound: entry and exit points and the tissue normal, from the observation's
  ``entry_point.*``, ``exit_point.*``, ``surface_normal.*`` and ``throw.index`` features when the arm reports
  them (a registration that follows the phantom), else from ``wound`` in the config; without either, no throw
  is guarded and actions pass unchanged.

Only the target's position changes: the tip's commanded end point becomes ``tip + v_safe * control_dt``. The
guarantee needs an arm whose Cartesian controller moves the tip in a straight line towards that point
(``suture_sim`` with ``--robot.tip_tracking=true``), within the margin less the grasp model's error, and a
declared ``latency_steps`` at least the arm's. A commanded pose with no rotation (zero or parallel columns)
becomes "hold the measured pose", with a warning, rather than ending the run.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from lerobot.configs.types import PipelineFeatureType, PolicyFeature
from lerobot.processor import ProcessorStepRegistry, RobotActionProcessorStep, TransitionKey

from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.safety.tip_guard import GuardResult, TipGuard
from lerobot_suture.safety.wound import GraspModel, Wound
from lerobot_suture.sim.psm import MAX_LINEAR_SPEED
from lerobot_suture.sim.task import CONTROL_DT, WORKSPACE_HIGH, WORKSPACE_LOW

from .config_suture_sim import POSE_FEATURES

WOUND_FEATURES = tuple(
    f"{point}.{axis}" for point in ("entry_point", "exit_point", "surface_normal") for axis in "xyz"
)
"""The registered wound as scalar observation features (m; the normal is a unit vector)."""
THROW_FEATURE = "throw.index"
"""Which throw the registered wound is (a running suture's throws 0-3)."""
GRASP_FEATURES = ("needle_grasp.angle", "needle_grasp.offset", "needle_grasp.roll")
"""The needle in the jaw as measured: arc angle (rad), offset along the jaw (m), roll (rad)."""
REGISTRATION_FEATURES = (*WOUND_FEATURES, THROW_FEATURE, *GRASP_FEATURES)


def _pose(values: dict, name: str) -> np.ndarray:
    missing = [key for key in POSE_FEATURES if key not in values]
    if missing:
        raise ValueError(
            f"suture_cbf needs the needle holder's pose in the {name}; it lacks {missing}. The arm must report "
            f"{POSE_FEATURES} (as suture_sim does)."
        )
    return np.array([float(values[key]) for key in POSE_FEATURES], dtype=np.float64)


@ProcessorStepRegistry.register("suture_cbf")
@dataclass
class SutureCBFStep(RobotActionProcessorStep):
    """The needle tip's CBF on the robot path (see the module docstring).

    Args:
        cbf: the filter (``CBFConfig`` or a dict of its fields); ``enabled=False`` only monitors.
        grasp: the grasp model used when the observation carries none (``GraspModel`` or a dict).
        wound: a fixed registration, 9 numbers (entry point, exit point, surface normal; m), used when the
            observation carries none; None: only the observation's.
        control_dt: the arm's control period (s): how long the commanded motion takes.
        held_jaw_range: measured jaw closures at which the jaw may hold the needle (``TipGuard``).
        latency_steps: the arm's declared latency (observation plus command, control steps >= 0): how long a
            command may stay in flight and a grasp go unseen (``TipGuard``).
        max_tip_speed: the arm's largest tip speed (m/s; ``suture_sim``'s by default), or None: commands are
            slowed to it relative to moving tissue, so the arm does not fall behind it (``TipGuard``).
        workspace_low, workspace_high: the box (m) the arm clips target positions to (``suture_sim``'s by
            default); a filtered target outside it becomes "hold the measured pose". None: no box.

    ``last_result`` is the :class:`GuardResult` of the last action (None before the first).
    """

    cbf: CBFConfig | dict = field(default_factory=lambda: CBFConfig(enabled=True))
    grasp: GraspModel | dict = field(default_factory=GraspModel)
    wound: list[float] | None = None
    control_dt: float = CONTROL_DT
    held_jaw_range: tuple[float, float] = (0.45, 0.97)
    latency_steps: int = 0
    max_tip_speed: float | None = MAX_LINEAR_SPEED
    workspace_low: list[float] | None = field(default_factory=lambda: WORKSPACE_LOW.tolist())
    workspace_high: list[float] | None = field(default_factory=lambda: WORKSPACE_HIGH.tolist())

    def __post_init__(self):
        if isinstance(self.cbf, dict):
            self.cbf = CBFConfig(**self.cbf)
        if isinstance(self.grasp, dict):
            self.grasp = GraspModel(**self.grasp)
        if not (isinstance(self.control_dt, int | float) and 0 < self.control_dt <= 1.0):
            raise ValueError(f"`control_dt` must be in (0, 1] s. Got {self.control_dt!r}.")
        self._fixed_wound = None
        if self.wound is not None:
            values = np.asarray(self.wound, dtype=np.float64).reshape(-1)
            if values.shape != (9,):
                raise ValueError(
                    f"`wound` must be 9 numbers: entry point, exit point, surface normal (m). Got {self.wound!r}."
                )
            self._fixed_wound = Wound(values[:3], values[3:6], values[6:9])
        self._workspace = None
        if (self.workspace_low is None) != (self.workspace_high is None):
            raise ValueError("`workspace_low` and `workspace_high` must both be given, or both be None.")
        if self.workspace_low is not None:
            low = np.asarray(self.workspace_low, dtype=np.float64).reshape(-1)
            high = np.asarray(self.workspace_high, dtype=np.float64).reshape(-1)
            if low.shape != (3,) or high.shape != (3,) or not np.all(low < high):
                raise ValueError(
                    f"`workspace_low` and `workspace_high` must be 3 numbers each (m), low < high. "
                    f"Got {self.workspace_low!r}, {self.workspace_high!r}."
                )
            self._workspace = (low, high)
        self._guard = TipGuard(
            self.cbf, tuple(self.held_jaw_range), self.latency_steps, max_tip_speed=self.max_tip_speed
        )
        self.last_result: GuardResult | None = None

    @property
    def phase(self) -> str:
        """The throw's phase: ``idle``, ``active`` or ``done``."""
        return self._guard.phase

    @property
    def throw_index(self) -> int | None:
        """The throw the phase is of, as the last registration said (None before the first)."""
        return self._guard.throw_index

    def registered_wound(self, observation: dict) -> Wound | None:
        """The wound the observation registers, else the configured one, else None."""
        if all(key in observation for key in WOUND_FEATURES):
            values = np.array([float(observation[key]) for key in WOUND_FEATURES])
            throw = int(observation.get(THROW_FEATURE, 0))
            return Wound(values[:3], values[3:6], values[6:9], throw_index=throw)
        return self._fixed_wound

    def grasp_model(self, observation: dict) -> GraspModel:
        """The grasp the observation reports, else the configured one."""
        if all(key in observation for key in GRASP_FEATURES):
            angle, offset, roll = (float(observation[key]) for key in GRASP_FEATURES)
            return GraspModel(angle=angle, offset_along_jaw=offset, roll=roll, radius=self.grasp.radius)
        return self.grasp

    def action(self, action: dict) -> dict:
        observation = self.transition.get(TransitionKey.OBSERVATION) or {}
        measured = _pose(observation, "observation")
        target = _pose(action, "action")
        safe, self.last_result = self._guard.filter_target(
            measured,
            target,
            self.registered_wound(observation),
            self.grasp_model(observation),
            self.control_dt,
            self._workspace,
        )
        out = dict(action)
        out.update({key: float(value) for key, value in zip(POSE_FEATURES, safe, strict=True)})
        return out

    def reset(self) -> None:
        self._guard.reset()
        self.last_result = None

    def get_config(self) -> dict[str, Any]:
        cbf, grasp = self.cbf, self.grasp
        return {
            "cbf": {name: getattr(cbf, name) for name in cbf.__dataclass_fields__},
            "grasp": {name: getattr(grasp, name) for name in grasp.__dataclass_fields__},
            "wound": None if self.wound is None else [float(v) for v in self.wound],
            "control_dt": float(self.control_dt),
            "held_jaw_range": [float(v) for v in self.held_jaw_range],
            "latency_steps": int(self.latency_steps),
            "max_tip_speed": None if self.max_tip_speed is None else float(self.max_tip_speed),
            "workspace_low": None if self.workspace_low is None else [float(v) for v in self.workspace_low],
            "workspace_high": None
            if self.workspace_high is None
            else [float(v) for v in self.workspace_high],
        }

    def transform_features(
        self, features: dict[PipelineFeatureType, dict[str, PolicyFeature]]
    ) -> dict[PipelineFeatureType, dict[str, PolicyFeature]]:
        return features
