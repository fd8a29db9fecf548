"""The scripted expert's plan for ``pickup``: reach over the needle lying on the phantom, lower the open jaw
onto it, close, and lift it clear.

From privileged state (the needle's true pose on the pad, the jaw's pose), it aims the jaw at the grasp an
insertion needs (``geometry.grasp_transform`` at the nominal arc angle, depth and roll):

1. ``reach``: carry the open jaw to ``approach_height`` above that grasp pose, turned into it;
2. ``lower``: lower it until the wire sits at the jaw tip;
3. ``close``: close the jaw (the capture rule of ``sim.needle_capture`` decides whether it caught the
   needle);
4. ``lift``: lift the jaw straight up until all of the needle is ``LIFT_MARGIN`` beyond
   ``pickup.LIFT_HEIGHT`` clear of the tissue; ``hold``: stay there.

A jaw that closed on nothing, or caught the needle in a grasp no throw starts from, opens (``open``) and
reaches again. Every step re-reads the needle, so it follows a needle the phantom carries away.
"""

from __future__ import annotations

import numpy as np

from lerobot_suture.sim.geometry import (
    grasp_transform,
    jaw_holding,
    pose_vector,
    rotvec_from_matrix,
    step_towards,
)
from lerobot_suture.sim.pickup import LIFT_HEIGHT, grasp_ready_for_throw
from lerobot_suture.sim.task import GRASP_ANGLE

PICKUP_PHASES = ("reach", "lower", "close", "lift", "hold", "open")
LIFT_MARGIN = 0.003
"""How far beyond ``pickup.LIFT_HEIGHT`` the expert lifts (m), so the pickup completes while it moves."""


class PickupPlan:
    """One pickup's phases; ``act(env)`` returns a (10,) float32 pose action.

    Args:
        config: the expert's speeds and tolerances (``expert.ExpertConfig``).
    """

    def __init__(self, config):
        self.config = config
        self.phase = "reach"
        self._lift_goal: np.ndarray | None = None

    def act(self, env) -> np.ndarray:
        u, cfg = env.unwrapped, self.config
        dt = u.control_dt
        jaw_pos, jaw_rot = u.jaw_pose()
        normal = u.phantom_rotation[:, 2]
        if self.phase == "close":
            if not u.needle_grasped:
                self.phase = "open"
            elif not grasp_ready_for_throw(u.grasp_parameters, u.grasp_reversed):
                self.phase = "open"
            else:
                self.phase = "lift"
                # Lift until all of the needle clears the tissue, however it lay in the jaw.
                rise = LIFT_HEIGHT + LIFT_MARGIN - u.needle_clearance
                self._lift_goal = jaw_pos + max(rise, 0.0) * normal
        if self.phase == "open":
            self.phase = "reach"
            return pose_vector(jaw_pos + cfg.approach_height * 0.25 * normal, jaw_rot, 0.0).astype(np.float32)
        if self.phase in ("lift", "hold") and not u.needle_grasped:
            self.phase = "open"  # the jaw lost the needle: start over from where it lies
        if self.phase == "open":
            self.phase = "reach"
            return pose_vector(jaw_pos + cfg.approach_height * 0.25 * normal, jaw_rot, 0.0).astype(np.float32)
        if self.phase in ("lift", "hold"):
            goal = self._lift_goal
            if self.phase == "lift" and np.linalg.norm(goal - jaw_pos) < cfg.position_tolerance:
                self.phase = "hold"
            target_pos, _ = step_towards(jaw_pos, jaw_rot, goal, jaw_rot, cfg.descend_speed * dt, 0.0)
            return pose_vector(target_pos, jaw_rot, 1.0).astype(np.float32)

        grasp_pos, grasp_rot = grasp_transform(GRASP_ANGLE, 0.0, 0.0)
        grasp_jaw_pos, grasp_jaw_rot = jaw_holding(*u.needle_pose(), grasp_pos, grasp_rot)
        above = grasp_jaw_pos + cfg.approach_height * normal
        if self.phase == "reach":
            turn = np.linalg.norm(rotvec_from_matrix(jaw_rot.T @ grasp_jaw_rot))
            if np.linalg.norm(above - jaw_pos) < cfg.position_tolerance and turn < cfg.angle_tolerance:
                self.phase = "lower"
            else:
                target = step_towards(
                    jaw_pos,
                    jaw_rot,
                    above,
                    grasp_jaw_rot,
                    cfg.approach_speed * dt,
                    cfg.approach_turn_rate * dt,
                )
                return pose_vector(*target, 0.0).astype(np.float32)
        # lower
        if np.linalg.norm(grasp_jaw_pos - jaw_pos) < cfg.position_tolerance:
            self.phase = "close"
            return pose_vector(grasp_jaw_pos, grasp_jaw_rot, 1.0).astype(np.float32)
        target = step_towards(
            jaw_pos,
            jaw_rot,
            grasp_jaw_pos,
            grasp_jaw_rot,
            cfg.descend_speed * dt,
            cfg.approach_turn_rate * dt,
        )
        return pose_vector(*target, 0.0).astype(np.float32)
