"""Needle insertion, and the suturing tasks around it, with a da Vinci-style instrument arm, in MuJoCo
(Gymnasium env).

## Description
A patient-side manipulator (PSM: remote centre of motion at the port, outer yaw and pitch,
insertion, instrument roll, wrist pitch and yaw, a jaw) holds a semicircular suture needle
(radius 0.010 m) over a suture phantom: a tissue pad with a wound line and two marked points on
either side of it. The needle must enter the tissue at the entry point and emerge at the exit point
by turning about its own centre, and protrude far enough to be grasped. An endoscope looks at the
work site. The phantom's pose changes between episodes, so a visuomotor policy must servo to it.

Physics runs at ``physics_dt`` = 0.002 s; the policy acts at ``control_dt`` = 0.1 s (10 Hz), so
one env step is 50 physics steps.

## Tasks
``task`` picks one of ``tasks.TASKS`` (each also registered under its own gym id):

- ``insertion`` (default, the paper's): the needle starts in the jaw; drive it from the entry to the exit
  point (the rest of this docstring describes it).
- ``pickup``: the needle lies on the phantom (``pickup``: its pose region) and the jaw starts open. A jaw
  closing on the needle catches it by the rule of ``needle_capture``; success is a grasp inside the ranges
  ``insertion`` is tested in, lifted ``pickup.LIFT_HEIGHT`` clear of the tissue (``pickup``). Terminated
  on success.
- ``extraction``: the needle starts driven through the tissue, held at its tail (``extraction``). Released,
  the tissue holds it; success is the needle regrasped and pulled all out along its arc, its tail leaving
  through the exit hole, the tissue strain within ``extraction.STRAIN_BOUND``. Terminated on success.
- ``running_suture``: four entry-and-exit pairs along the wound (``running_suture``), the needle starting in
  the jaw. Each throw is scored as an insertion; once over on the marks, the needle must be extracted through
  the exit hole (as ``extraction`` scores it) before the next throw begins. Terminated on a throw off the marks
  or when the fourth throw is over; success is all four on the marks. ``info`` adds ``throw_index``,
  ``throw_phase`` (``insert`` or ``extract``), ``throws_on_marks``, ``throws_extracted`` and ``throw_results``
  (per throw: entry and exit errors, on the marks, extracted).

## Action Space
``Box(10,)``, float32: the target pose of the needle holder (the jaw tip frame ``jaw_tip``) at the
end of the control step, in the world frame.

=====  ================================================  ======================  ====
index  meaning                                           range                   unit
=====  ================================================  ======================  ====
0-2    jaw tip position x, y, z                          ``task.WORKSPACE_LOW``  m
                                                         to ``..._HIGH``
3-5    first column of the jaw rotation matrix           [-1, 1]                 --
6-8    second column of the jaw rotation matrix          [-1, 1]                 --
9      jaw closure (1 closed, < 0.5 opens and releases   [0, 1]                  --
       the needle)
=====  ================================================  ======================  ====

The env turns the action into a Cartesian velocity command (reach the target in one control step,
speed-limited), expresses it at the needle tip while the needle is held, passes the needle tip's
linear velocity through ``tip_velocity_filter`` (the one point where a safety filter such as the CBF
acts), maps the twist to joint velocities by damped differential inverse kinematics at the needle
tip, and the arm's velocity actuators track those at physics rate. While a filter is installed the
inverse kinematics puts the tip's linear velocity first, inside the joints' speed and range bounds,
and the rotation in its null space (``controller.tip_first_velocity_ik``), re-solved 10 times per
control step with feedback towards the filtered segment, so the tip goes where the filter allowed.
Values outside the action space are clipped; a wrong shape, NaN or inf raise ``ValueError``.

## Observation Space
``obs_type="pixels_agent_pos"`` (default, the paper's): ``{"pixels": {"endoscope": (H, W, 3) uint8},
"agent_pos": (10,) float32}`` where ``agent_pos`` is the measured jaw pose in the action's layout. Its
jaw closure reads about 0.88 while the jaw holds the needle, since the wire keeps the jaws apart (the
exact value depends on where along the jaw it sits), and 1 once a closed jaw has lost it.
With ``wrist_camera=True`` ``pixels`` also holds ``"wrist"``, the image of a camera on the instrument's
shaft (``lerobot_suture.sim.wrist_camera``): the scene's look is the endoscope's, without the endoscope's
pose jitter and image effects.
``obs_type="state"``: ``{"agent_pos", "environment_state"}`` with no image, for fast
low-dimensional experiments; ``obs_type="pixels_agent_pos_state"``: all three.
``environment_state`` (18,) float32 is privileged: entry point (3), exit point (3), needle centre
(3), needle rotation first two columns (6), needle tip (3).

## Rewards
1.0 on the step the insertion succeeds, else 0.0 (``info["reward_success"]``).

## Starting State
The phantom's position is uniform within ``task.PHANTOM_RANGE_XY`` of the nominal one and its yaw
within ``task.PHANTOM_YAW_RANGE``; the grasp angle on the needle within 4 degrees of the nominal, its
offset along the jaw and its roll slightly (``task.GRASP_RANGES["narrow"]``; ``grasp="wide"`` widens all
three); the arm starts near its home pose above the site. All randomness comes from ``self.np_random``
(seeded by ``reset(seed=...)``).

## Episode End
Terminated when the throw is over: the tip has emerged and protrudes at least ``task.MIN_PROTRUSION``
beyond where it left the tissue, the needle still spanning the wound. It succeeded
(``info["is_success"]``) if the tip entered within ``task.ENTRY_TOLERANCE`` of the entry point and emerged
within ``task.EXIT_TOLERANCE`` of the exit point; a throw off the marks is over too, since driving on only
pulls the needle further through the wrong holes. Truncated by the registered ``max_episode_steps``
(100 = 10 s).

## Info
``is_success``; ``reward_success`` (the reward's only term); ``entry_error_m`` and ``exit_error_m``
(distance in the tissue surface from the marked point to where the tip crossed it, m; ``inf`` until
the tip has entered / emerged); ``protrusion_m`` (tip distance beyond the exit crossing, m);
``tissue_strain`` (accumulated off-arc motion of the needle in tissue, m); ``needle_tip_pos`` (3,);
``needle_in_tissue``; ``needle_grasped``; ``perturbed`` (the scenario's perturbation has begun);
``tip_velocity_nominal`` and ``tip_velocity_command`` (3,) m/s (before and after
``tip_velocity_filter``); with ``record_tip_trace``, ``needle_tip_trace`` (50, 3) m and the same points in the
phantom's frame at each physics step, ``needle_tip_trace_phantom`` (50, 3) m (the phantom moves continuously in
the scenarios that move it).

## Appearance randomization
``appearance`` varies what the endoscope sees, per episode, without changing the physics: each option is
a range, 0 (off) by default. Drawn once per episode at ``reset`` from a generator spawned from
``self.np_random`` (the phantom, grasp and arm draws, hence the trajectories, are those of the same seed
without it; with every option off nothing is drawn and the images are those of an env without it).
Scene options edit the MuJoCo model and are restored and redrawn at every reset; haze, blur and noise
are applied to the endoscope observation only (not to ``render()`` frames). The drawn look is
``appearance_sample``.

The options, their ranges and their draws are tabled in ``lerobot_suture.sim.appearance``. The needle and the entry and exit markers keep their look. ``lerobot_suture.sim.appearance`` has the
details; the dataset card lists a recording's ranges.

## Arguments
=======================  ======================  ===============================================
argument                 default                 meaning
=======================  ======================  ===============================================
``obs_type``             ``"pixels_agent_pos"``  observation layout (see above)
``image_size``           ``96``                  endoscope image side (px): small for CPU training
``render_mode``          ``"rgb_array"``         only ``rgb_array``
``render_size``          ``256``                 side (px) of ``render()`` frames (videos)
``scenario``             ``"nominal"``           perturbation scenario (``scenarios.SCENARIOS``)
``scenario_onset_step``  ``None``                onset step (None: the scenario's default)
``scenario_magnitude``   ``None``                magnitude (None: the scenario's default)
``record_tip_trace``     ``False``               step physics one at a time and return the needle
                                                 tip after every physics step in
                                                 ``info["needle_tip_trace"]`` (slower)
``tip_tracking``         ``False``               while the needle is held, drive its tip in a
                                                 straight line to where the target pose puts
                                                 it, tip-first (the controller a CBF outside
                                                 the env, on the robot path, relies on)
``grasp``                ``"narrow"``            grasp randomization (``task.GRASP_RANGES``): ``narrow``
                                                 (the test scenes) or ``wide`` (demonstrations
                                                 that make the needle's pose matter)
``appearance``           ``None``                appearance randomization (see above): an
                                                 ``appearance.AppearanceConfig``, a dict of its
                                                 fields, or None (all off)
``task``                 ``"insertion"``         the task (``tasks.TASKS``; see Tasks above):
                                                 ``insertion``, ``pickup``,
                                                 ``extraction`` or ``running_suture``
``wrist_camera``         ``False``               add the wrist camera's image to ``pixels``
=======================  ======================  ===============================================
"""

from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces

from lerobot_suture.sim.actuation import InstrumentDrive, TipVelocityFilter
from lerobot_suture.sim.appearance import (
    AppearanceConfig,
    AppearanceSample,
    EpisodeAppearance,
    SceneAppearance,
)
from lerobot_suture.sim.endoscope import Endoscope
from lerobot_suture.sim.geometry import (
    jaw_holding,
    needle_arc_points,
    pose_vector,
    quat_from_matrix,
    rot6_from_matrix,
    rotation_about_z,
)
from lerobot_suture.sim.grasp import NeedleGrasp
from lerobot_suture.sim.privileged_state import PrivilegedState
from lerobot_suture.sim.psm import PSM
from lerobot_suture.sim.scenarios import Scenario, ScenarioConfig
from lerobot_suture.sim.scene_model import scene_model
from lerobot_suture.sim.task import (
    CONTROL_DT,
    GRASP_RANGES,
    PHANTOM_NOMINAL,
    PHANTOM_RANGE_XY,
    PHANTOM_YAW_RANGE,
    WORKSPACE_HIGH,
    WORKSPACE_LOW,
)
from lerobot_suture.sim.task_scenes import TaskScenes
from lerobot_suture.sim.tasks import DEFAULT_TASK, check_scenario, task_spec
from lerobot_suture.sim.wrist_camera import WristCamera

OBS_TYPES = ("pixels_agent_pos", "state", "pixels_agent_pos_state")
IMAGE_SIDE_RANGE = (16, 640)  # px; the upper bound is the offscreen buffer of scene.xml


def check_image_side(name: str, value: int) -> None:
    """Raise a ValueError naming ``name`` unless ``value`` (px) lies in :data:`IMAGE_SIDE_RANGE`."""
    low, high = IMAGE_SIDE_RANGE
    if not low <= int(value) <= high:
        raise ValueError(f"`{name}` must be in [{low}, {high}] px. Got {value}.")


_N_ARC_POINTS = 13
NEEDLE_KEYPOINTS = 3
"""Points of the needle located in the image by ``needle_keypoints_in_image``: tip, middle, tail."""


class SutureEnv(TaskScenes, PrivilegedState, gym.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": int(round(1.0 / CONTROL_DT))}

    def __init__(
        self,
        obs_type: str = "pixels_agent_pos",
        image_size: int = 96,
        render_mode: str | None = "rgb_array",
        render_size: int = 256,
        scenario: str = "nominal",
        scenario_onset_step: int | None = None,
        scenario_magnitude: float | None = None,
        record_tip_trace: bool = False,
        tip_tracking: bool = False,
        grasp: str = "narrow",
        appearance: AppearanceConfig | dict | None = None,
        task: str = DEFAULT_TASK,
        wrist_camera: bool = False,
    ):
        self.task_spec = task_spec(task)
        check_scenario(task, scenario)
        if obs_type not in OBS_TYPES:
            raise ValueError(f"`obs_type` must be one of {OBS_TYPES}. Got {obs_type!r}.")
        check_image_side("image_size", image_size)
        if wrist_camera and "pixels" not in obs_type:
            raise ValueError(f"`wrist_camera` adds an image; `obs_type`={obs_type!r} has none.")
        if grasp not in GRASP_RANGES:
            raise ValueError(f"`grasp` must be one of {list(GRASP_RANGES)}. Got {grasp!r}.")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"`render_mode` must be 'rgb_array' or None. Got {render_mode!r}.")
        check_image_side("render_size", render_size)
        self.obs_type = obs_type
        self.image_size = int(image_size)
        self.render_mode = render_mode
        self.render_size = int(render_size)
        self.record_tip_trace = bool(record_tip_trace)
        self.tip_tracking = bool(tip_tracking)
        self.grasp = grasp
        if scenario_onset_step is None:
            scenario_onset_step = self.task_spec.default_onset(scenario)
        self.scenario = Scenario(
            ScenarioConfig(name=scenario, onset_step=scenario_onset_step, magnitude=scenario_magnitude),
            CONTROL_DT,
        )

        self.appearance = AppearanceConfig.from_value(appearance)

        self.model = scene_model(task, self.appearance.tissue_texture > 0, wrist_camera)
        self.data = mujoco.MjData(self.model)
        self.physics_dt = float(self.model.opt.timestep)
        self.control_dt = CONTROL_DT
        self.n_substeps = int(round(self.control_dt / self.physics_dt))

        m = self.model
        self._arm = PSM(m)
        self._grasp = NeedleGrasp(m, self._arm)
        self._phantom_mocap = m.body("phantom").mocapid[0]
        self._endoscope = Endoscope(m, self.image_size, self.render_size)
        self._wrist = WristCamera(m, self.image_size) if wrist_camera else None
        self._look = EpisodeAppearance(
            self.appearance, SceneAppearance(m), self._endoscope, [self._wrist] if self._wrist else []
        )
        self._entry_local = m.site("entry_point").pos.copy()
        self._exit_local = m.site("exit_point").pos.copy()
        self._arc_local = needle_arc_points(_N_ARC_POINTS)
        self._tip_local = self._arc_local[0]
        self._keypoints_local = needle_arc_points(NEEDLE_KEYPOINTS)
        self.drive = InstrumentDrive(m, self.data, self._arm, self._grasp, self._tip_local, self.n_substeps)

        self.action_space = spaces.Box(
            low=np.concatenate([WORKSPACE_LOW, -np.ones(6), [0.0]]).astype(np.float32),
            high=np.concatenate([WORKSPACE_HIGH, np.ones(6), [1.0]]).astype(np.float32),
            dtype=np.float32,
        )
        obs_spaces: dict[str, spaces.Space] = {}
        if "pixels" in obs_type:
            image = spaces.Box(0, 255, (self.image_size, self.image_size, 3), dtype=np.uint8)
            obs_spaces["pixels"] = spaces.Dict(
                {"endoscope": image, **({"wrist": image} if wrist_camera else {})}
            )
        obs_spaces["agent_pos"] = spaces.Box(-np.inf, np.inf, (10,), dtype=np.float32)
        if obs_type in ("state", "pixels_agent_pos_state"):
            obs_spaces["environment_state"] = spaces.Box(-np.inf, np.inf, (18,), dtype=np.float32)
        self.observation_space = spaces.Dict(obs_spaces)

        self.tip_velocity_filter: TipVelocityFilter | None = None
        """None or f(needle_tip_pos (3,) m, v_nominal (3,) m/s) -> v_safe (3,) m/s; called once per
        control step while the needle is held, before inverse kinematics."""

        self._home_qpos = self._solve_home_pose()
        self._reset_state()

    # ------------------------------------------------------------------ what LeRobot reads
    @property
    def task_name(self) -> str:
        """Which task of ``tasks.TASKS`` this env simulates."""
        return self.task_spec.name

    @property
    def task_description(self) -> str:
        """The task in words: ``lerobot-eval`` asks every (async) worker for it through ``env.call``."""
        return self.task_spec.instruction

    @property
    def task(self) -> str:
        """The task string; LeRobot's fallback when ``task_description`` is missing."""
        return self.task_spec.instruction

    # ------------------------------------------------------------------ scenario hooks
    def release_needle(self) -> None:
        """The jaw loses the needle: it keeps its current velocity and falls under gravity."""
        self._grasp.release(self.data, in_tissue=self._progress.in_tissue)

    def set_grasp(self, angle: float, offset_along_jaw: float, roll: float) -> None:
        """Hold the needle with another grasp than this episode's draw (arc angle rad, offset along the
        jaw m, roll rad; ``geometry.grasp_transform``), the held needle moved into it at once."""
        self._grasp.set(angle, offset_along_jaw, roll)
        if self._grasp.held:
            self._grasp.snap_needle(self.data)

    def set_phantom_pose(self, position: np.ndarray, yaw: float) -> None:
        """Move the phantom (mocap) to ``position`` (3,) m with ``yaw`` rad about the world z axis. A needle
        resting on it (``grasp``) moves with it, as static friction would carry it."""
        if self._grasp.resting:
            centre, rotation = self.needle_pose()
            move = rotation_about_z(float(yaw) - self._phantom_yaw)
            new_centre = np.asarray(position, dtype=np.float64) + move @ (centre - self._phantom_pos)
            self._grasp.place_free_needle(self.data, new_centre, move @ rotation)
        self._phantom_pos = np.asarray(position, dtype=np.float64).copy()
        self._phantom_yaw = float(yaw)
        self._phantom_rot = rotation_about_z(self._phantom_yaw)
        self.data.mocap_pos[self._phantom_mocap] = self._phantom_pos
        self.data.mocap_quat[self._phantom_mocap] = quat_from_matrix(self._phantom_rot)

    def clip_to_phantom_range(self, xy: np.ndarray) -> np.ndarray:
        """Clip a phantom (x, y) position (m) into the training range."""
        return np.clip(xy, PHANTOM_NOMINAL[:2] - PHANTOM_RANGE_XY, PHANTOM_NOMINAL[:2] + PHANTOM_RANGE_XY)

    def set_appearance(self, sample: AppearanceSample) -> None:
        """Show ``sample``'s look for the rest of the episode, in place of the one ``reset`` drew: a fixed
        shift of appearance (``lerobot_suture.sim.shifts``). The next ``reset`` draws (or restores) the
        configured look again. A mottled tissue needs ``appearance.tissue_texture`` > 0 at construction
        (the texture is part of the model); without it the contrast is ignored."""
        self._look.set(sample, self.np_random)

    def set_endoscope_viewpoint(self, azimuth_offset: float = 0.0, elevation_offset: float = 0.0) -> None:
        """Place the endoscope on its sphere about the work site, offset from the training view (rad)."""
        self._endoscope.set_viewpoint(azimuth_offset, elevation_offset)

    def observe(self, needle_visible: bool = True) -> dict:
        """The observation of the current state (what the last ``reset``/``step`` returned).

        With ``needle_visible=False`` the endoscope image is rendered without the needle, the scene left
        as it is: a probe of whether a policy reads the needle from the image
        (``studies/benchmarks/needle_attention.py``).
        """
        if needle_visible:
            return self._observation()
        needle_geoms = np.flatnonzero(self.model.geom_bodyid == self._grasp.needle_body)
        alpha = self.model.geom_rgba[needle_geoms, 3].copy()
        self.model.geom_rgba[needle_geoms, 3] = 0.0
        try:
            return self._observation()
        finally:
            self.model.geom_rgba[needle_geoms, 3] = alpha

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        rng = self.np_random
        self._reset_state()
        mujoco.mj_resetData(self.model, self.data)
        self._look.draw(rng)
        self.set_endoscope_viewpoint()

        xy = PHANTOM_NOMINAL[:2] + rng.uniform(-PHANTOM_RANGE_XY, PHANTOM_RANGE_XY, size=2)
        self.set_phantom_pose(
            np.array([xy[0], xy[1], PHANTOM_NOMINAL[2]]), rng.uniform(-1, 1) * PHANTOM_YAW_RANGE
        )
        self._set_up_task(rng)
        self.scenario.reset(self)
        self._update_tissue_state(first=True)
        info = self._info(success=False, v_nominal=np.zeros(3), v_command=np.zeros(3))
        info.update(self._task_info())
        return self._observation(), info

    def step(self, action):
        target = self._validated_action(action)
        self.scenario.before_step(self)
        phantom_trace: list[tuple[np.ndarray, np.ndarray]] = []
        place_phantom = None
        if self.scenario.moving:
            start = self._step_index * self.control_dt

            def place_phantom(elapsed: float) -> None:
                self.set_phantom_pose(*self.scenario.phantom_pose(start + elapsed))
                phantom_trace.append((self._phantom_pos.copy(), self._phantom_rot.copy()))

        drive = self.drive.step(
            target,
            self.tip_velocity_filter,
            self._progress.in_tissue,
            self.record_tip_trace,
            self.tip_tracking,
            place_phantom,
        )
        self._step_index += 1
        if self._first_grasp_step is None and self._grasp.held:
            self._first_grasp_step = self._step_index
        self._after_physics()
        self._update_tissue_state()
        terminated, success = self._task_outcome()
        reward = 1.0 if success else 0.0
        info = self._info(success=success, v_nominal=drive.v_nominal, v_command=drive.v_command)
        info.update(self._task_info())
        if drive.tip_trace is not None:
            info["needle_tip_trace"] = drive.tip_trace
            info["needle_tip_trace_phantom"] = self.in_phantom_frame(drive.tip_trace, phantom_trace)
        return self._observation(), reward, terminated, False, info

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        return self._endoscope.video_frame(self.data)

    def close(self):
        self._endoscope.close()
        if self._wrist is not None:
            self._wrist.close()

    # ------------------------------------------------------------------ internals
    def _reset_state(self) -> None:
        self._step_index = 0
        self._grasp.reset(held=self.task_name != "pickup")
        self._first_grasp_step = 0 if self._grasp.held else None
        self._start_throw(0)
        self._phantom_pos = PHANTOM_NOMINAL.copy()
        self._phantom_yaw = 0.0
        self._phantom_rot = np.eye(3)

    def _validated_action(self, action) -> np.ndarray:
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (10,):
            raise ValueError(
                f"action must have shape (10,) (jaw position 3, rotation columns 6, jaw 1). Got shape {a.shape}."
            )
        if not np.all(np.isfinite(a)):
            bad = np.flatnonzero(~np.isfinite(a)).tolist()
            raise ValueError(f"action contains NaN or inf at indices {bad}: {a.tolist()}.")
        return np.clip(a, self.action_space.low, self.action_space.high)

    def _solve_home_pose(self) -> np.ndarray:
        """Arm joints that hold the nominal needle 25 mm above the nominal throw (kinematic IK)."""
        self._reset_state()
        frame = self.insertion_frame()
        centre = frame.centre + np.array([0.0, 0.0, 0.025])
        target_pos, target_rot = jaw_holding(centre, frame.start_rotation, *self.grasp_in_jaw)
        mujoco.mj_resetData(self.model, self.data)
        return self._arm.solve_jaw_pose(self.data, target_pos, target_rot)

    def _update_tissue_state(self, first: bool = False) -> None:
        self._progress.update(
            *self.needle_pose(), self._phantom_pos, self._phantom_rot, self._step_index, first
        )

    def _observation(self) -> dict:
        jaw_pos, jaw_rot = self.jaw_pose()
        obs: dict = {
            "agent_pos": pose_vector(jaw_pos, jaw_rot, self._grasp.jaw_closure(self.data)).astype(np.float32)
        }
        if "pixels" in self.obs_type:
            obs["pixels"] = {"endoscope": self._look.degrade(self._endoscope.image(self.data))}
            if self._wrist is not None:
                obs["pixels"]["wrist"] = self._wrist.image(self.data)
        if self.obs_type in ("state", "pixels_agent_pos_state"):
            centre, rot = self.needle_pose()
            obs["environment_state"] = np.concatenate(
                [self.entry_point, self.exit_point, centre, rot6_from_matrix(rot), self._progress.tip_world]
            ).astype(np.float32)
        return obs

    def _info(self, success: bool, v_nominal: np.ndarray, v_command: np.ndarray) -> dict:
        # Python bools: a vector env fills an env that has not finished with False only for those (a NumPy
        # bool gets an object array with None, which lerobot-eval cannot stack).
        return {
            "is_success": bool(success),
            "reward_success": 1.0 if success else 0.0,
            "entry_error_m": self._progress.entry_error,
            "exit_error_m": self._progress.exit_error,
            "protrusion_m": self._progress.protrusion,
            "tissue_strain": self._progress.strain,
            "needle_tip_pos": self._progress.tip_world.copy(),
            "needle_in_tissue": bool(self._progress.in_tissue),
            "needle_grasped": bool(self._grasp.held),
            "grasp_parameters": np.array(self._grasp.parameters, dtype=np.float64),
            "perturbed": bool(self.scenario.perturbed),
            "tip_velocity_nominal": np.asarray(v_nominal, dtype=np.float64).copy(),
            "tip_velocity_command": np.asarray(v_command, dtype=np.float64).copy(),
        }
