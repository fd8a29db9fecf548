"""The privileged state of the suture scene: what the scripted expert, the metrics and the scenario
hooks read from the simulator, and what a policy never sees.

A mixin of :class:`~lerobot_suture.sim.suture_env.SutureEnv`: it reads the env's scene handles (the arm,
the grasp, the endoscope, the phantom's pose, the insertion's progress) and never writes them.
"""

from __future__ import annotations

import numpy as np

from lerobot_suture.sim.appearance import AppearanceSample
from lerobot_suture.sim.geometry import InsertionFrame, grasp_transform, insertion_frame
from lerobot_suture.sim.grasp import CaptureVerdict
from lerobot_suture.sim.pickup import LIFT_HEIGHT, clearance, grasp_ready_for_throw
from lerobot_suture.sim.task import GRASP_ANGLE, NEEDLE_TILT


class PrivilegedState:
    """Read-only views of the scene, in world coordinates, metres and radians."""

    @property
    def step_index(self) -> int:
        """Control steps taken since reset."""
        return self._step_index

    @property
    def phantom_position(self) -> np.ndarray:
        """(3,) centre of the tissue pad's top surface, world (m)."""
        return self._phantom_pos

    @property
    def phantom_yaw(self) -> float:
        return self._phantom_yaw

    @property
    def phantom_rotation(self) -> np.ndarray:
        """(3, 3) world-from-phantom rotation; phantom z is the tissue normal, x runs entry->exit."""
        return self._phantom_rot

    def in_phantom_frame(self, trace: np.ndarray, phantom_trace: list | None = None) -> np.ndarray:
        """(n, 3) m points of a physics-rate ``trace`` in the phantom's frame at each physics step: the phantom's
        (position, rotation) per step in ``phantom_trace``, or its pose now when it did not move."""
        if not phantom_trace:
            return (trace - self._phantom_pos) @ self._phantom_rot
        positions = np.stack([position for position, _ in phantom_trace])
        rotations = np.stack([rotation for _, rotation in phantom_trace])
        return np.einsum("nij,ni->nj", rotations, trace - positions)

    @property
    def entry_point(self) -> np.ndarray:
        return self._phantom_pos + self._phantom_rot @ self._entry_local

    @property
    def exit_point(self) -> np.ndarray:
        return self._phantom_pos + self._phantom_rot @ self._exit_local

    @property
    def needle_grasped(self) -> bool:
        return self._grasp.held

    @property
    def needle_in_tissue(self) -> bool:
        return self._progress.in_tissue

    @property
    def jaw_closure_command(self) -> float:
        """The last jaw closure command, in [0, 1] (1 closed; the jaw closes on the needle as it reaches 0.5)."""
        return self._grasp.closure_command

    def capture_verdict(self) -> CaptureVerdict:
        """What the jaw would do with the free needle if it closed now (``grasp.NeedleGrasp.capture_verdict``)."""
        return self._grasp.capture_verdict(self.data, self.needle_in_tissue)

    @property
    def needle_touched_tissue(self) -> bool:
        return self._progress.first_in_tissue_step is not None

    @property
    def tail_exit_error(self) -> float:
        """Distance in the tissue surface from the exit point to where the needle's tail left the tissue
        (m); inf until it has."""
        return self._progress.tail_exit_error

    @property
    def first_grasp_step(self) -> int | None:
        """Control step at which the jaw first held the needle this episode (0 when it starts held), or None."""
        return self._first_grasp_step

    @property
    def wire_diameter(self) -> float:
        """The needle wire's diameter (m)."""
        return self._grasp.wire_diameter

    @property
    def throw_index(self) -> int:
        """The throw in progress (0-based; the running suture has four, every other task one)."""
        return self._throw

    @property
    def needle_in_throw_grasp(self) -> bool:
        """The jaw holds the needle in a grasp a throw starts from (``pickup.grasp_ready_for_throw``)."""
        return self._grasp.held and grasp_ready_for_throw(self._grasp.parameters, self._grasp.reversed)

    @property
    def throw_phase(self) -> str:
        """``insert`` until the throw is over, then (running suture) ``extract`` until the needle is out."""
        return self._throw_phase

    @property
    def approach_over(self) -> bool:
        """The approach a ``phantom_servo`` perturbs is over: the needle has touched tissue, or, in
        ``pickup``, the jaw has caught it."""
        if self.task_name == "pickup":
            return self._first_grasp_step is not None
        return self._throw > 0 or self.needle_touched_tissue

    @property
    def first_in_tissue_step(self) -> int | None:
        return self._progress.first_in_tissue_step

    @property
    def grasp_in_jaw(self) -> tuple[np.ndarray, np.ndarray]:
        """The needle's pose in the jaw-tip frame: (position (3,) m, rotation (3, 3))."""
        return self._grasp.position, self._grasp.rotation

    @property
    def grasp_parameters(self) -> tuple[float, float, float]:
        """This episode's grasp: (arc angle rad, offset along the jaw m, roll rad); see
        ``geometry.grasp_transform``."""
        return self._grasp.parameters

    @property
    def grasp_reversed(self) -> bool:
        """The jaw caught the needle the other way round from any grasp a throw starts from."""
        return self._grasp.reversed

    @property
    def nominal_grasp_in_jaw(self) -> tuple[np.ndarray, np.ndarray]:
        """The grasp before its per-episode randomization: (position (3,) m, rotation (3, 3)) in the jaw."""
        return grasp_transform(GRASP_ANGLE, 0.0, 0.0)

    @property
    def appearance_sample(self) -> AppearanceSample | None:
        """This episode's draw of ``appearance`` (None when every option is off)."""
        return self._look.sample

    @property
    def needle_clearance(self) -> float:
        """Height of the needle's lowest point above the tissue surface (m)."""
        centre, rotation = self.needle_pose()
        return clearance(centre + self._arc_local @ rotation.T, self._phantom_pos, self._phantom_rot)

    @property
    def needle_picked_up(self) -> bool:
        """The jaw holds the needle ready for a throw, all of it ``pickup.LIFT_HEIGHT`` clear of the tissue:
        ``pickup``'s success."""
        return self.needle_in_throw_grasp and self.needle_clearance >= LIFT_HEIGHT

    @property
    def needle_tip_pos(self) -> np.ndarray:
        centre, rotation = self.needle_pose()
        return centre + rotation @ self._tip_local

    def needle_keypoints_in_image(self) -> np.ndarray:
        """The needle's tip, middle and tail in the endoscope image: (6,) float32 ``[x, y]`` per point,
        normalized to [-1, 1] (x right, y down; see ``geometry.project_to_image``).

        Privileged (the simulator's needle pose): recorded as a training target that teaches an image encoder
        where the needle is, never an input a policy acts on.
        """
        self._endoscope.update_poses(self.data)
        centre, rotation = self.needle_pose()
        return self._endoscope.project(self.data, centre + self._keypoints_local @ rotation.T)

    def jaw_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Measured jaw-tip pose, world: (position (3,) m, rotation (3, 3))."""
        return self._arm.jaw_pose(self.data)

    def needle_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Needle centre and orientation, world: (position (3,) m, rotation (3, 3))."""
        return self._grasp.needle_pose(self.data)

    def insertion_frame(self) -> InsertionFrame:
        """Where the needle must be to pass from the current entry point to the exit point."""
        return insertion_frame(self.entry_point, self.exit_point, self._phantom_rot[:, 2], NEEDLE_TILT)
