"""The expert's label at a state the policy visits (ungated DAgger), from the privileged simulator state.

The scripted expert (:mod:`lerobot_suture.expert`) is a phase machine (approach, descend, drive, hold) that
advances its phase only on waypoints it reaches within its tolerances (0.5 mm, 0.03 rad). Watching a
policy that never passes exactly through its approach waypoint, it would stay in its approach phase all
episode and label every state, the needle already in tissue included, "carry the needle back up to the
approach pose". So the labeller places the expert's phase on the state the policy reached before asking
for its action:

- when the needle enters (or leaves) the tissue the phase is worked out afresh, as at a surgeon's takeover
  (in tissue: drive on from the needle's current angle about its centre);
- out of tissue, a needle inside the descend corridor (its centre within ``CORRIDOR_SLACK`` position
  tolerances (m) of the line from the entry pose up to the approach waypoint along the phantom's normal,
  no higher than the waypoint, and turned less than ``CORRIDOR_SLACK`` angle tolerances (rad) from the
  throw's start orientation) is descending;
- otherwise the expert keeps its own phase from step to step (its approach, and its detour when it has one).

With the expert itself driving, the labels are its actions.
"""

from __future__ import annotations

import numpy as np

from lerobot_suture.expert import ExpertConfig, ScriptedExpert
from lerobot_suture.sim.geometry import needle_in_world, rotvec_from_matrix

CORRIDOR_SLACK = 4.0
"""The descend corridor's width in the expert's tolerances (the factor it passes its detour waypoint by)."""


def in_descend_corridor(u, config: ExpertConfig) -> bool:
    """Whether the needle, out of tissue, sits where the expert's descent runs (see the module docstring).

    Args:
        u: the unwrapped suture env.
        config: the expert's settings (tolerances, approach height, which grasp it plans with).
    """
    jaw_pos, jaw_rot = u.jaw_pose()
    grasp_pos, grasp_rot = u.nominal_grasp_in_jaw if config.assume_nominal_grasp else u.grasp_in_jaw
    centre, rotation = needle_in_world(jaw_pos, jaw_rot, grasp_pos, grasp_rot)
    frame = u.insertion_frame()
    normal = u.phantom_rotation[:, 2]
    offset = centre - frame.centre  # (3,) m
    height = float(offset @ normal)
    lateral = float(np.linalg.norm(offset - height * normal))
    turn = float(np.linalg.norm(rotvec_from_matrix(rotation.T @ frame.start_rotation)))
    slack = CORRIDOR_SLACK * config.position_tolerance
    return (
        lateral <= slack
        and -slack <= height <= config.approach_height - slack
        and turn <= CORRIDOR_SLACK * config.angle_tolerance
    )


class StateLabeller:
    """``label(env)``: the expert's (10,) action at the env's current state; ``reset(env)`` per episode."""

    def __init__(self, config: ExpertConfig):
        self.config = config
        self.expert = ScriptedExpert(config)
        self._in_tissue: bool | None = None

    def reset(self, env) -> None:
        self.expert.reset(env)
        self._in_tissue = None

    def label(self, env) -> np.ndarray:
        u = env.unwrapped
        in_tissue = bool(u.needle_in_tissue)
        if in_tissue != self._in_tissue:
            self.expert.phase = None  # worked out afresh from the state at the next act
        elif not in_tissue and self.expert.phase in ("detour", "approach") and u.needle_grasped:
            if in_descend_corridor(u, self.config):
                self.expert.phase = "descend"
        self._in_tissue = in_tissue
        return self.expert.act(env)  # reads the state, moves nothing
