"""The scripted expert's plan for ``extraction``: let go of the needle's tail, regrasp it near its tip, and
pull it out along its arc.

From privileged state (the needle's true pose, lodged in the tissue, and the jaw's pose):

1. ``release``: open the jaw; the tissue holds the needle;
2. ``back_off``: draw the open jaw back along its axis, off the wire;
3. ``reach``: carry it to ``BACK_OFF`` short of a grasp at ``extraction.REGRASP_ANGLE`` from the tip, turning
   it about its own axis against the pull's sense (the long way round), so that the instrument's roll has the
   pull's half turn left; ``advance``: onto the wire;
4. ``settle``: with ``regrasp_settle`` > 0, hold the open jaw on the grasp for that many control steps;
   ``close``: close the jaw (``sim.needle_capture`` decides whether it caught the needle);
5. ``pull``: turn the needle about its own centre at ``drive_rate``, so every point follows the arc out
   through the exit hole, until the tail is ``PULL_MARGIN`` past it; ``hold``: stay there.

With ``regrasp_reach_offset`` > 0 each reach ends beside the point short of the grasp, by an offset across
and along the jaw drawn per reach, and the advance corrects it on the way onto the grasp.

A jaw that missed, or lost the needle, backs off and reaches again for the needle where it now lies. Every
step re-reads the phantom, so the pull follows a phantom that moves. With ``regrasp_miss`` > 0 the first
reach aims that far beside the needle, across the jaw (the side drawn from the episode's seed and the
throw), so the jaw closes beside the lodged needle and the plan shows its recovery. With ``regrasp_aim``
``"marks"`` every reach aims at the grasp planned through the registered marks
(``sim.extraction.planned_regrasp``) instead of the needle's true pose; with ``"release"`` at the grasp planned
from the jaw's pose when it let go (``sim.regrasp_target.released_regrasp``), which is the plan's first act.
"""

from __future__ import annotations

import math

import numpy as np

from lerobot_suture.expert_plans import episode_stream
from lerobot_suture.sim.extraction import (
    BACK_OFF,
    PULL_MARGIN,
    REGRASP_ANGLE,
    planned_regrasp,
    reach_step,
    turn_left,
)
from lerobot_suture.sim.geometry import (
    grasp_transform,
    jaw_holding,
    pose_vector,
    step_towards,
)
from lerobot_suture.sim.regrasp_target import released_regrasp

EXTRACTION_PHASES = ("release", "back_off", "reach", "advance", "settle", "close", "pull", "hold")
_MISS_STREAM = 0x3155  # mixed with the env's seed: the miss side's own stream, apart from the env's draws
_REACH_STREAM = 0x3156  # the reach offsets' own stream


class ExtractionPlan:
    """One extraction's phases; ``act(env)`` returns a (10,) float32 pose action.

    Args:
        config: the expert's speeds and tolerances (``expert.ExpertConfig``).
    """

    def __init__(self, config):
        self.config = config
        self.phase = "release"
        self.drive_angle = 0.0
        self._goal: np.ndarray | None = None
        self._aim_beside: float | None = None  # m across the jaw; None until the first act draws it
        self._release: tuple[np.ndarray, np.ndarray] | None = None  # the jaw's pose when it let go
        self._settled = 0  # control steps the open jaw has held the grasp
        # Each reach's offset (2,) m along x and y of the grasp's frame (None: draw anew), and its generator.
        self._reach_offset: np.ndarray | None = None
        self._reach_rng: np.random.Generator | None = None

    @property
    def regrasping(self) -> bool:
        """Whether the plan is reaching for the regrasp (``reach``, ``advance`` or ``settle``)."""
        return self.phase in ("reach", "advance", "settle")

    def _miss_offset(self, u) -> float:
        """How far across the jaw (m) the current reach aims beside the needle: ``regrasp_miss`` on the
        first reach, to a side drawn from the episode's seed and throw, then 0."""
        if self._aim_beside is None:
            rng = episode_stream(
                getattr(u, "np_random_seed", None), _MISS_STREAM, getattr(u, "throw_index", 0)
            )
            self._aim_beside = self.config.regrasp_miss * (1.0 if rng.integers(2) else -1.0)
        return self._aim_beside

    def _offset_of_reach(self, u) -> np.ndarray:
        """Where (m, along x and y of the grasp's frame) the current reach ends beside the point short of the
        grasp: uniform in a disc of radius ``regrasp_reach_offset``, drawn once per reach."""
        if self._reach_offset is None:
            if self._reach_rng is None:
                self._reach_rng = episode_stream(
                    getattr(u, "np_random_seed", None), _REACH_STREAM, getattr(u, "throw_index", 0)
                )
            radius = self.config.regrasp_reach_offset * math.sqrt(self._reach_rng.random())
            angle = 2.0 * math.pi * self._reach_rng.random()
            self._reach_offset = radius * np.array([math.cos(angle), math.sin(angle)])
        return self._reach_offset

    def act(self, env) -> np.ndarray:
        u, cfg = env.unwrapped, self.config
        dt = u.control_dt
        jaw_pos, jaw_rot = u.jaw_pose()
        frame = u.insertion_frame()
        if self.phase == "close":
            if u.needle_grasped:
                self.phase = "pull"
                relative = frame.start_rotation.T @ u.needle_pose()[1]
                self.drive_angle = (-math.atan2(relative[1, 0], relative[0, 0])) % (2.0 * math.pi)
            else:
                self.phase = "back_off"
                self._goal = None
            self._aim_beside = 0.0  # a reach after a closing aims at the needle
            self._reach_offset = None
        elif self.phase in ("pull", "hold") and not u.needle_grasped:
            self.phase, self._goal = "back_off", None  # lost it: reach for it where it lies
        if self.phase == "release":
            self._release = (jaw_pos, jaw_rot)
            self.phase = "back_off"
            return pose_vector(jaw_pos, jaw_rot, 0.0).astype(np.float32)
        if self.phase == "back_off":
            if self._goal is None:
                self._goal = jaw_pos - BACK_OFF * jaw_rot[:, 2]
            if np.linalg.norm(self._goal - jaw_pos) < cfg.position_tolerance:
                self.phase = "reach"
            else:
                target = step_towards(jaw_pos, jaw_rot, self._goal, jaw_rot, cfg.approach_speed * dt, 0.0)
                return pose_vector(*target, 0.0).astype(np.float32)
        if self.phase in ("reach", "advance", "settle"):
            if cfg.regrasp_aim == "marks":
                grasp_pos, grasp_rot = planned_regrasp(u.entry_point, u.exit_point, u.phantom_rotation[:, 2])
            elif cfg.regrasp_aim == "release":
                grasp_pos, grasp_rot = released_regrasp(*self._release)
            else:
                grasp_pos, grasp_rot = jaw_holding(
                    *u.needle_pose(), *grasp_transform(REGRASP_ANGLE, 0.0, 0.0)
                )
            grasp_pos = grasp_pos + self._miss_offset(u) * grasp_rot[:, 1]  # the faces close along y
            if self.phase == "reach":
                short = grasp_pos + grasp_rot[:, :2] @ self._offset_of_reach(u) - BACK_OFF * grasp_rot[:, 2]
                left = turn_left(jaw_rot, grasp_rot)
                if np.linalg.norm(short - jaw_pos) < cfg.position_tolerance and left < cfg.angle_tolerance:
                    self.phase = "advance"
                else:
                    step = reach_step(
                        jaw_pos,
                        jaw_rot,
                        short,
                        grasp_rot,
                        left,
                        cfg.approach_speed * dt,
                        cfg.approach_turn_rate * dt,
                    )
                    return pose_vector(*step, 0.0).astype(np.float32)
            if self.phase == "settle" or np.linalg.norm(grasp_pos - jaw_pos) < cfg.position_tolerance:
                if self._settled < cfg.regrasp_settle:
                    self.phase, self._settled = "settle", self._settled + 1
                    return pose_vector(grasp_pos, grasp_rot, 0.0).astype(np.float32)
                self.phase, self._settled = "close", 0
                return pose_vector(grasp_pos, grasp_rot, 1.0).astype(np.float32)
            target = step_towards(
                jaw_pos, jaw_rot, grasp_pos, grasp_rot, cfg.descend_speed * dt, cfg.approach_turn_rate * dt
            )
            return pose_vector(*target, 0.0).astype(np.float32)
        # pull / hold: the needle turns about its centre; the jaw holds it as it was caught.
        final = math.pi + frame.exit_angle + PULL_MARGIN
        if self.phase == "pull":
            self.drive_angle = min(final, self.drive_angle + cfg.drive_rate * dt)
            if self.drive_angle >= final:
                self.phase = "hold"
        target = jaw_holding(frame.centre, frame.needle_rotation(self.drive_angle), *u.grasp_in_jaw)
        return pose_vector(*target, 1.0).astype(np.float32)
