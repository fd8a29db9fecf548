"""The scripted expert's plan for ``running_suture``: for each of the four throws, insert, extract, lay the
needle down and pick it up again at its tail, then go on to the next pair.

It strings the other tasks' plans together, chosen from the env's state at every step:

- ``insert``: the needle held in a grasp a throw starts from (``pickup.grasp_ready_for_throw``) and the throw
  not yet over, or the insertion still driving on to its planned protrusion: the insertion expert
  (``expert.ScriptedExpert`` for ``insertion``) at the throw's pair;
- ``extract``: the throw is over and on the marks: ``expert_plans.extraction.ExtractionPlan``;
- ``lay_down``: the needle held near its tip after an extraction: carry it flat above the phantom beside the
  wound (``pickup``'s resting place), the jaw pointing down, and open the jaw ``LAY_DOWN_HEIGHT`` above it;
- ``pick_up``: the needle lies on the phantom: ``expert_plans.pickup.PickupPlan``.

One arm does all of it. Regrasping the needle at its tail by laying it down is slower than handing it to a
second instrument, as a surgeon would, but needs no second arm.
"""

from __future__ import annotations

import numpy as np

from lerobot_suture.expert_plans.extraction import ExtractionPlan
from lerobot_suture.expert_plans.pickup import PickupPlan
from lerobot_suture.sim.geometry import (
    jaw_holding,
    pose_vector,
    rotation_about_x,
    rotation_about_z,
    rotvec_from_matrix,
    step_towards,
)
from lerobot_suture.sim.pickup import REST_CENTRE, REST_YAW, grasp_ready_for_throw

LAY_DOWN_HEIGHT = 0.001
"""Height of the needle's wire above the tissue surface where the jaw lets it go (m)."""


class LayDownPlan:
    """Carry the held needle flat over its resting place, then open the jaw."""

    def __init__(self, config):
        self.config = config
        self.phase = "carry"

    def act(self, env) -> np.ndarray:
        u, cfg = env.unwrapped, self.config
        dt = u.control_dt
        jaw_pos, jaw_rot = u.jaw_pose()
        if self.phase == "release":
            return pose_vector(jaw_pos, jaw_rot, 0.0).astype(np.float32)
        phantom_rot = u.phantom_rotation
        local = np.array([*REST_CENTRE, 0.5 * u.wire_diameter + LAY_DOWN_HEIGHT])
        centre = u.phantom_position + phantom_rot @ local
        rotation = phantom_rot @ rotation_about_z(REST_YAW) @ rotation_about_x(np.pi)
        goal_pos, goal_rot = jaw_holding(centre, rotation, *u.grasp_in_jaw)
        turn = float(np.linalg.norm(rotvec_from_matrix(jaw_rot.T @ goal_rot)))
        if np.linalg.norm(goal_pos - jaw_pos) < cfg.position_tolerance and turn < cfg.angle_tolerance:
            self.phase = "release"
            return pose_vector(jaw_pos, jaw_rot, 0.0).astype(np.float32)
        # Rise first, clear of the tissue, then carry and lower.
        above = goal_pos + cfg.approach_height * phantom_rot[:, 2]
        near = (
            np.linalg.norm((above - jaw_pos)[:2]) < cfg.position_tolerance * 4 and turn < cfg.angle_tolerance
        )
        waypoint = goal_pos if near or self.phase == "lower" else above
        if near:
            self.phase = "lower"
        speed = cfg.descend_speed if self.phase == "lower" else cfg.approach_speed
        target = step_towards(jaw_pos, jaw_rot, waypoint, goal_rot, speed * dt, cfg.approach_turn_rate * dt)
        return pose_vector(*target, 1.0).astype(np.float32)


class RunningSuturePlan:
    """The running suture's stages (module docstring); ``act(env)`` returns a (10,) float32 pose action."""

    def __init__(self, config, insertion_expert_factory):
        self.config = config
        self._new_insertion_expert = insertion_expert_factory
        self.stage: str | None = None
        self._plan = None
        self._throw = -1

    @property
    def regrasping(self) -> bool:
        """Whether the current stage's plan is reaching for an extraction's regrasp."""
        return getattr(self._plan, "regrasping", False)

    @property
    def phase(self) -> str | None:
        """``stage/phase`` of the plan in use."""
        return None if self.stage is None else f"{self.stage}/{self._plan.phase}"

    def act(self, env) -> np.ndarray:
        u = env.unwrapped
        stage = self._stage(u)
        if stage != self.stage or u.throw_index != self._throw:
            self.stage, self._throw = stage, u.throw_index
            if stage == "insert":
                self._plan = self._new_insertion_expert()
                self._plan.reset(env)
            else:
                self._plan = {"extract": ExtractionPlan, "lay_down": LayDownPlan, "pick_up": PickupPlan}[
                    stage
                ](self.config)
        return self._plan.act(env)

    def _stage(self, u) -> str:
        if u.throw_phase == "extract":
            # Let the insertion drive on to its planned protrusion before letting go.
            driving = self.stage == "insert" and self._plan.phase not in ("hold", None)
            return "insert" if driving and u.needle_grasped else "extract"
        if u.needle_grasped:
            if grasp_ready_for_throw(u.grasp_parameters, u.grasp_reversed):
                return "insert"
            return "lay_down"
        if self.stage == "lay_down" and self._plan.phase == "release":
            return "pick_up"
        return "pick_up"
