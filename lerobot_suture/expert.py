"""A scripted expert for every task of the family, from privileged simulator state.

``ScriptedExpert.act`` follows the plan of the env's task: ``expert_plans.pickup.PickupPlan``,
``expert_plans.extraction.ExtractionPlan``, ``expert_plans.running_suture.RunningSuturePlan``, or, for
``insertion``, the plan below. It reads the true needle grasp, the entry and exit points and the needle's
pose from the env (as the paper's demonstrator reads AMBF's state) and emits the same 10-dim pose actions a
policy emits:

0. ``detour`` (only with ``approach_detour`` > 0): carry the needle first to a waypoint ``approach_detour``
   to one side of the entry-exit line, at ``approach_height``; the side is drawn per episode from the env's
   seed, so the demonstrations hold two equally valid ways into the same throw (a bimodal approach);
1. ``approach``: carry the needle to ``approach_height`` above its throw pose, its plane through the
   entry-exit line (tilted towards the arm's port), the tip above the entry point;
2. ``descend``: lower it until the tip rests on the entry point;
3. ``drive``: turn it about its own centre by the arc angle between entry and exit plus
   ``protrusion_angle``, so the tip emerges from the exit point far enough to be grasped;
4. ``hold``: stay there.

With ``regrasp_noise`` > 0 the expert demonstrates in the manner of DART: while it reaches for an extraction's
regrasp (``ExtractionPlan.regrasping``), :meth:`ScriptedExpert.executed` adds Gaussian noise to the jaw position
of the action the env executes, and :func:`iter_expert_steps` records the expert's own action as the label; the
expert then corrects what the noise did, and recovers a closing it makes beside the needle.

Every step re-reads the phantom, so the expert servos to a moving phantom. It also stands in for the
surgeon after a handover: ``reset`` with the env mid-episode works out the phase from the state (a
needle already in tissue is driven on from its current angle). A needle the jaw has lost in
``insertion`` is not re-grasped by this expert; it then holds the arm still.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from lerobot_suture.checks import check_positive
from lerobot_suture.expert_plans import episode_stream
from lerobot_suture.expert_plans.extraction import ExtractionPlan
from lerobot_suture.expert_plans.pickup import PickupPlan
from lerobot_suture.expert_plans.running_suture import RunningSuturePlan
from lerobot_suture.sim.geometry import (
    jaw_holding,
    needle_in_world,
    pose_vector,
    rotvec_from_matrix,
    step_towards,
)
from lerobot_suture.sim.relative_actions import env_action
from lerobot_suture.sim.task import (
    ANGLE_TOLERANCE,
    APPROACH_SPEED,
    DESCEND_SPEED,
    DRIVE_RATE,
    POSITION_TOLERANCE,
    TURN_RATE,
)

PHASES = ("detour", "approach", "descend", "drive", "hold")
REGRASP_AIMS = ("needle", "marks", "release")
"""What an extraction's regrasp may aim at (``ExpertConfig.regrasp_aim``)."""
MAX_REGRASP_SETTLE = 10
"""The longest the expert holds a regrasp's pose before it closes (control steps)."""
MAX_REGRASP_REACH_OFFSET = 0.003
"""The farthest a regrasp's reach may end beside the point short of the grasp (m): the 6 mm advance corrects it."""
_SIDE_STREAM = 0x51DE  # mixed with the env's seed: the detour side's own stream, apart from the env's draws
_NOISE_STREAM = 0xDA27  # mixed with the env's seed: the executed noise's own stream


@dataclass
class ExpertConfig:
    """Speeds and tolerances of the scripted expert (m, m/s, rad, rad/s).

    Args:
        approach_height: height of the needle centre above its throw pose before descending (m).
        approach_speed: needle-centre speed during the approach (m/s).
        approach_turn_rate: needle turning rate during the approach (rad/s).
        descend_speed: needle-centre speed while lowering the tip onto the entry point (m/s).
        drive_rate: turning rate about the needle centre while driving through tissue (rad/s).
        protrusion_angle: how far past the exit point the needle is driven (rad of arc).
        position_tolerance: distance to a waypoint that counts as reached (m).
        angle_tolerance: angle to a waypoint orientation that counts as reached (rad).
        approach_detour: lateral offset of the detour waypoint from the throw's approach pose (m); 0 (the
            default) approaches straight, > 0 via either side, drawn per episode.
        regrasp_noise: standard deviation (m, per axis, drawn every control step) of the noise on the executed
            jaw position while the expert reaches for an extraction's regrasp; the recorded label stays the
            expert's action (DART, module docstring). 0 (the default): the executed action is the label.
        regrasp_miss: how far (m) the first regrasp of each extraction aims beside the needle, across the jaw
            (the side drawn per extraction): 0 (the default) aims at it; 0.0006 to 0.003 closes the jaw beside
            the lodged needle, so the demonstration shows a missed regrasp and the reach again that recovers it
            (``expert_plans.extraction``).
        regrasp_aim: what an extraction's regrasp aims at: ``"needle"`` (the default), the needle's true pose;
            ``"marks"``, the grasp planned through the registered marks (``extraction.planned_regrasp``), which
            a policy with the ``regrasp_target`` observation is given, so its labels follow from what it reads;
            ``"release"``, the grasp planned from where the jaw let go of the needle
            (``regrasp_target.released_regrasp``), what that observation gives with ``regrasp_from="release"``.
        regrasp_settle: control steps the open jaw holds the regrasp's pose before it closes (0: it closes as it
            arrives, within ``position_tolerance``). A settled closing is judged where the jaw stands still on the
            grasp, so a policy that learns it may close a step late without closing beside the needle.
        regrasp_reach_offset: how far (m, at most) the reach for each regrasp ends beside the point short of
            the grasp, across the jaw and along it (drawn per reach from the episode's seed); the advance
            then carries the jaw onto the grasp, so the demonstration corrects a reach that ended off, as a
            policy's does. The closing itself is still on the grasp (unlike ``regrasp_miss``).
        assume_nominal_grasp: plan with the env's nominal grasp of the needle instead of the true one, as a
            policy that cannot see how the needle sits in the jaw must: an upper bound on such a policy's
            success, a lower bound on its entry error (``benchmarks/expert_quality.py
            --assume-nominal-grasp``). Never for recording.
    """

    approach_height: float = 0.012
    approach_speed: float = APPROACH_SPEED
    approach_turn_rate: float = TURN_RATE
    descend_speed: float = DESCEND_SPEED
    drive_rate: float = DRIVE_RATE
    protrusion_angle: float = 0.5
    position_tolerance: float = POSITION_TOLERANCE
    angle_tolerance: float = ANGLE_TOLERANCE
    approach_detour: float = 0.0
    regrasp_miss: float = 0.0
    regrasp_noise: float = 0.0
    regrasp_aim: str = "needle"
    regrasp_settle: int = 0
    regrasp_reach_offset: float = 0.0
    assume_nominal_grasp: bool = False

    def __post_init__(self):
        check_positive(
            self,
            (
                "approach_height",
                "approach_speed",
                "approach_turn_rate",
                "descend_speed",
                "drive_rate",
                "protrusion_angle",
                "position_tolerance",
                "angle_tolerance",
            ),
        )
        if not (0.0 <= self.approach_detour <= 0.03 and math.isfinite(self.approach_detour)):
            raise ValueError(
                f"`approach_detour` must be in [0, 0.03] m (0: a straight approach). Got {self.approach_detour}."
            )
        if not (0.0 <= self.regrasp_noise <= 0.002):
            raise ValueError(
                f"`regrasp_noise` must be in [0, 0.002] m (0: the executed action is the label). "
                f"Got {self.regrasp_noise}."
            )
        if not (self.regrasp_miss == 0.0 or 0.0006 <= self.regrasp_miss <= 0.003):
            raise ValueError(
                f"`regrasp_miss` must be 0 (aim at the needle) or in [0.0006, 0.003] m, beside it by more than "
                f"the jaw's capture tolerance. Got {self.regrasp_miss}."
            )
        if not (isinstance(self.regrasp_settle, int) and 0 <= self.regrasp_settle <= MAX_REGRASP_SETTLE):
            raise ValueError(
                f"`regrasp_settle` must be a whole number of control steps in [0, {MAX_REGRASP_SETTLE}] (0: the "
                f"jaw closes as it arrives). Got {self.regrasp_settle!r}."
            )
        if not (0.0 <= self.regrasp_reach_offset <= MAX_REGRASP_REACH_OFFSET):
            raise ValueError(
                f"`regrasp_reach_offset` must be in [0, {MAX_REGRASP_REACH_OFFSET}] m (0: the reach ends in line "
                f"with the grasp). Got {self.regrasp_reach_offset}."
            )
        if self.regrasp_aim not in REGRASP_AIMS:
            raise ValueError(f"`regrasp_aim` must be one of {REGRASP_AIMS}. Got {self.regrasp_aim!r}.")


class ScriptedExpert:
    """Privileged needle-insertion expert; ``act(env)`` returns a (10,) float32 pose action."""

    def __init__(self, config: ExpertConfig | None = None, task: str | None = None):
        self.config = config or ExpertConfig()
        self.task = task
        """The task whose plan it follows; None: the env's (``task_name``)."""
        self.phase: str | None = None
        self.drive_angle = 0.0
        self.detour_side = 1.0
        self._plan: PickupPlan | ExtractionPlan | RunningSuturePlan | None = None
        self._noise = np.random.default_rng()

    def reset(self, env=None) -> None:
        """Start over; the phase is worked out from the env's state at the next ``act``. With
        ``approach_detour`` on, the detour's side (+1 or -1 along the throw's lateral axis) is drawn from the
        seed of ``env``'s last reset: the same seed takes the same side, and the side says nothing of the
        scene the seed draws."""
        self.phase = None
        self.drive_angle = 0.0
        self._plan: PickupPlan | ExtractionPlan | RunningSuturePlan | None = None
        seed = getattr(env.unwrapped, "np_random_seed", None) if env is not None else None
        self.detour_side = 1.0 if episode_stream(seed, _SIDE_STREAM).integers(2) else -1.0
        self._noise = episode_stream(seed, _NOISE_STREAM)

    def executed(self, action: np.ndarray) -> np.ndarray:
        """The action the env executes for the expert's ``action`` (its last :meth:`act`): the same, or, while it
        reaches for a regrasp with ``regrasp_noise`` on, its jaw position plus Gaussian noise (DART)."""
        if self.config.regrasp_noise == 0.0 or not getattr(self._plan, "regrasping", False):
            return action
        noisy = np.array(action, dtype=np.float32)
        noisy[:3] += self._noise.normal(0.0, self.config.regrasp_noise, 3).astype(np.float32)
        return noisy

    @property
    def stage(self) -> str | None:
        """The running suture's stage the expert is executing (``insert``, ``extract``, ``lay_down``, ``pick_up``;
        set by ``act``), None for the other tasks or before the first ``act``."""
        return getattr(self._plan, "stage", None)

    def act(self, env) -> np.ndarray:
        u = env.unwrapped
        cfg = self.config
        task = self.task or u.task_name
        if task != "insertion":
            if self._plan is None:
                if task == "running_suture":
                    self._plan = RunningSuturePlan(cfg, lambda: ScriptedExpert(cfg, task="insertion"))
                else:
                    self._plan = (PickupPlan if task == "pickup" else ExtractionPlan)(cfg)
            return self._plan.act(env)
        dt = u.control_dt
        jaw_pos, jaw_rot = u.jaw_pose()
        if not u.needle_grasped:
            return pose_vector(jaw_pos, jaw_rot, 1.0).astype(np.float32)

        frame = u.insertion_frame()
        grasp_pos, grasp_rot = u.nominal_grasp_in_jaw if cfg.assume_nominal_grasp else u.grasp_in_jaw
        # The needle as the expert believes it is held (the true pose unless it assumes the nominal grasp).
        centre, rotation = needle_in_world(jaw_pos, jaw_rot, grasp_pos, grasp_rot)
        normal = u.phantom_rotation[:, 2]
        if self.phase is None:
            self._infer_phase(u, frame, rotation)

        if self.phase == "detour":
            lateral = np.cross(normal, u.exit_point - u.entry_point)
            lateral /= np.linalg.norm(lateral)
            goal = (
                frame.centre + cfg.approach_height * normal + self.detour_side * cfg.approach_detour * lateral
            )
            if np.linalg.norm(goal - centre) < 4 * cfg.position_tolerance:  # a waypoint, passed loosely
                self.phase = "approach"
            else:
                target = step_towards(
                    centre, rotation, goal, rotation, cfg.approach_speed * dt, cfg.approach_turn_rate * dt
                )
        if self.phase == "approach":
            goal = frame.centre + cfg.approach_height * normal
            error = np.linalg.norm(goal - centre)
            turn = np.linalg.norm(rotvec_from_matrix(rotation.T @ frame.start_rotation))
            if error < cfg.position_tolerance and turn < cfg.angle_tolerance:
                self.phase = "descend"
            else:
                target = step_towards(
                    centre,
                    rotation,
                    goal,
                    frame.start_rotation,
                    cfg.approach_speed * dt,
                    cfg.approach_turn_rate * dt,
                )
        if self.phase == "descend":
            if np.linalg.norm(frame.centre - centre) < cfg.position_tolerance:
                self.phase = "drive"
            else:
                target = step_towards(
                    centre,
                    rotation,
                    frame.centre,
                    frame.start_rotation,
                    cfg.descend_speed * dt,
                    cfg.approach_turn_rate * dt,
                )
        final_angle = frame.exit_angle + cfg.protrusion_angle
        if self.phase == "drive":
            self.drive_angle = min(final_angle, self.drive_angle + cfg.drive_rate * dt)
            target = (frame.centre, frame.needle_rotation(self.drive_angle))
            if self.drive_angle >= final_angle:
                self.phase = "hold"
        elif self.phase == "hold":
            target = (frame.centre, frame.needle_rotation(final_angle))

        target_jaw_pos, target_jaw_rot = jaw_holding(*target, grasp_pos, grasp_rot)
        return pose_vector(target_jaw_pos, target_jaw_rot, 1.0).astype(np.float32)

    def _infer_phase(self, u, frame, rotation) -> None:
        if u.needle_in_tissue:
            # Angle already driven: the needle's turn from the start orientation about its axis.
            relative = frame.start_rotation.T @ rotation
            self.drive_angle = max(0.0, -math.atan2(relative[1, 0], relative[0, 0]))
            self.phase = "drive"
        else:
            self.phase = "detour" if self.config.approach_detour > 0 else "approach"


@dataclass(frozen=True)
class ExpertStep:
    """One control step of the expert: the observation it acted on, its action and what followed."""

    obs: dict
    needle_keypoints: np.ndarray | None  # (6,) the needle in the image of ``obs`` (privileged), if asked for
    action: np.ndarray
    reward: float
    terminated: bool
    truncated: bool
    info: dict

    @property
    def done(self) -> bool:
        return self.terminated or self.truncated


def iter_expert_steps(
    env,
    expert: ScriptedExpert,
    obs: dict,
    steps_after_success: int = 0,
    needle_keypoints: bool = False,
) -> Iterator[ExpertStep]:
    """Yield the expert's steps from ``obs``, the observation ``env.reset`` just returned, to the
    episode's end. A step's action is the expert's; the env executes :meth:`ScriptedExpert.executed` of it.

    Args:
        steps_after_success: control steps to go on after the step the insertion succeeds (where the env
            terminates); the last of them is yielded as the terminal step. 0: end at success.
        needle_keypoints: also locate the needle in the image of each step's observation
            (``SutureEnv.needle_keypoints_in_image``; a dataset's training target). Otherwise None.
    """
    if steps_after_success < 0:
        raise ValueError(f"`steps_after_success` must be >= 0. Got {steps_after_success}.")
    expert.reset(env)
    remaining = None  # control steps left once the insertion has succeeded
    while True:
        keypoints = env.unwrapped.needle_keypoints_in_image() if needle_keypoints else None
        target = expert.act(env)
        action = env_action(env, target)  # relative when the env takes relative actions
        executed = expert.executed(target)
        next_obs, reward, terminated, truncated, info = env.step(
            action if executed is target else env_action(env, executed)
        )
        if remaining is not None:
            remaining -= 1
        elif terminated and info["is_success"]:
            remaining = steps_after_success
        if remaining is not None:
            terminated = remaining == 0  # the episode, as recorded, ends after the extra steps
        yield ExpertStep(obs, keypoints, action, float(reward), bool(terminated), bool(truncated), info)
        if terminated or truncated:
            return
        obs = next_obs
