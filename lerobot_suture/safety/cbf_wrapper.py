"""The CBF installed at the env step: filters the needle tip's Cartesian velocity inside ``SutureEnv``.

``SutureEnv.step`` turns the action into a Cartesian velocity command for the needle tip, calls
``env.unwrapped.tip_velocity_filter(needle_tip_pos, v_nominal)`` once per control step, and runs
inverse kinematics on the velocity it gets back; the velocity is held for the whole control step
(``control_dt``, 0.1 s) while physics runs at ``physics_dt`` (2 ms). :class:`CBFActionWrapper` sets
that hook. Whatever produced the action (policy, scripted surgeon) is filtered the same way.

The wrapper is a thin user of :class:`~lerobot_suture.safety.tip_guard.TipGuard`, the filter and phase rules
that the robot path's ``suture_cbf`` processor step runs from measured kinematics: here the env supplies the
tip, its nominal velocity, the wound (its entry and exit markers) and whether it holds the needle, exactly.

The ellipsoid is :class:`~lerobot_suture.safety.cbf_config.CBFConfig`'s, centred midway between the phantom's
current entry and exit markers, with axes (entry->exit, lateral, tissue normal); it is rebuilt from the env
every control step, so it follows a moving phantom, whose measured motion the guard also filters against.

Safe set and guard (never in a task without a throw, ``pickup`` and ``extraction``): the tip of the held needle
may be above the tissue or in the ellipsoid, never in the tissue outside it (``tip_guard``). The filter acts on
every control step in which the env holds the needle, whatever the throw's phase; the phase (``cbf_active``)
reports the throw: it begins at the first control step where the needle is held in a grasp a throw starts from
(in a running suture, again at each throw) with its tip inside the margin-tightened ellipsoid, and ends when
the needle is released. ``reset`` starts over.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from lerobot_suture.safety.cbf import ellipsoid_h
from lerobot_suture.safety.cbf_config import CBFConfig
from lerobot_suture.safety.tip_guard import PHASE_ACTIVE, PHASE_DONE, PHASE_IDLE, TipGuard
from lerobot_suture.safety.wound import Wound
from lerobot_suture.sim.geometry import segment_distance

__all__ = ["PHASE_ACTIVE", "PHASE_DONE", "PHASE_IDLE", "CBFActionWrapper", "wound_in_phantom_frame"]

_NAN3 = np.full(3, np.nan)


def wound_in_phantom_frame(scene) -> Wound:
    """The current throw's wound of ``scene`` (a ``SutureEnv``) in the phantom's frame, where its marks stand
    still however the phantom moves (the frame of ``info["needle_tip_trace_phantom"]``)."""
    rotation, position = scene.phantom_rotation, scene.phantom_position
    return Wound(
        (scene.entry_point - position) @ rotation,
        (scene.exit_point - position) @ rotation,
        np.array([0.0, 0.0, 1.0]),
        throw_index=int(scene.throw_index),
    )


class CBFActionWrapper(gym.Wrapper):
    """Keeps the needle tip inside the safe ellipsoid around the wound during a suture throw.

    Info keys added to ``reset`` and every ``step``:

    ============== ========== =====================================================================
    key            type       meaning
    ============== ========== =====================================================================
    cbf_active     bool       the throw's phase was ``active`` during this step
    cbf_guarding   bool       the needle was held in a scene with a throw: the filter acted during this
                              step (or, disabled, watched)
    cbf_mode       str        the convex set the step was kept in: ``above``, ``wound`` or ""
    h              float      the ellipsoid's barrier at the needle tip after the step (>= 0 inside)
    v_nominal      (3,) m/s   tip velocity the action asked for (NaN if the env did not call the hook)
    v_safe         (3,) m/s   tip velocity sent to the robot (NaN if the env did not call the hook)
    cbf_intervened bool       ``v_safe`` differs from ``v_nominal``
    cbf_tracking_  float, m   distance from the tip at the end of the step to the end of the
    error                     commanded segment ``x + v_safe * control_dt`` (NaN while not guarding)
    cbf_segment_   float, m   largest distance from the tip to the commanded segment over the step's
    deviation                 physics-rate trace (the end point alone without ``needle_tip_trace``):
                              what the margin must cover (NaN while not guarding)
    cbf_filter_    float, s   wall time of the filter call (NaN while not guarding)
    time
    cbf_motion_    bool       the wound moved faster, or accelerated harder, than the configuration's
    exceeded                  declared bounds: outside the filter's premises (a rollout hands over)
    ============== ========== =====================================================================

    ``cbf_segment_deviation`` is the premise of the guarantee measured: every point within
    ``config.margin`` of the commanded segment is in the safe set, so the tip stays out of the tissue
    outside the ellipsoid at every physics step of a step whose deviation is at most the margin.

    With ``config.enabled`` False the wrapper only monitors: it tracks the phase and reports ``h``
    but sends ``v_nominal`` unchanged (useful as the "filter off" arm of a comparison).

    Args:
        env: an env whose ``unwrapped`` is a ``SutureEnv`` (has ``tip_velocity_filter``,
            ``entry_point``, ``exit_point``, ``phantom_rotation``, ``needle_tip_pos``,
            ``needle_in_tissue``, ``needle_grasped``, ``control_dt``, ``throw_index``, ``task_spec``, whose
            ``throws`` says how many throws the task has to guard, and, with more than one,
            ``needle_in_throw_grasp``).
        config: the filter's configuration; None means ``CBFConfig(enabled=True)``.

    Raises:
        TypeError: if the env has no ``tip_velocity_filter`` hook.
    """

    def __init__(self, env: gym.Env, config: CBFConfig | None = None):
        super().__init__(env)
        base = env.unwrapped
        if not hasattr(base, "tip_velocity_filter"):
            raise TypeError(
                "CBFActionWrapper needs an env with a `tip_velocity_filter` hook (SutureEnv); "
                f"got {type(base).__name__}."
            )
        self.config = CBFConfig(enabled=True) if config is None else config
        self._axes = self.config.semi_axes
        self._guard = TipGuard(self.config)
        self._record: tuple[bool, bool, str, np.ndarray, np.ndarray, bool, bool] | None = None
        # The step's commanded segment: start (m), end (m), and the filter call's time (s).
        self._segment: tuple[np.ndarray, np.ndarray, float] | None = None
        base.tip_velocity_filter = self._filter_tip_velocity

    @property
    def phase(self) -> str:
        """``idle``, ``active`` or ``done`` (see the module docstring)."""
        return self._guard.phase

    @property
    def guard(self) -> TipGuard:
        """The guard the hook runs (the robot path's ``suture_cbf`` runs the same class)."""
        return self._guard

    def safe_set(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The current safe ellipsoid from the env's entry/exit markers.

        Returns:
            (center (3,) m, semi-axes (3,) m, rotation (3, 3) world-from-ellipsoid).
        """
        center, rotation = self.wound().ellipsoid_frame()
        return center, self._axes, rotation

    def h_min(self, info: dict[str, Any]) -> float:
        """Smallest barrier of the safe set (:meth:`Wound.barrier`: >= 0 above the tissue or in the ellipsoid)
        over a step's physics-rate tip trace, ``info["needle_tip_trace_phantom"]``, against the wound where it
        was at each physics step (the env records it with ``record_tip_trace``)."""
        points = np.asarray(info["needle_tip_trace_phantom"], dtype=np.float64)
        return float(np.min(wound_in_phantom_frame(self.env.unwrapped).barrier(points, self._axes)))

    def wound(self) -> Wound:
        """The current throw's wound, from the env's entry and exit markers and the phantom's normal."""
        base = self.env.unwrapped
        normal = np.asarray(base.phantom_rotation, dtype=np.float64)[:, 2]
        return Wound(base.entry_point, base.exit_point, normal, throw_index=int(base.throw_index))

    def _filter_tip_velocity(self, needle_tip_pos: np.ndarray, v_nominal: np.ndarray) -> np.ndarray:
        """The hook SutureEnv calls while it holds the needle: (3,) tip position (m), (3,) nominal velocity
        (m/s) -> (3,) m/s."""
        base = self.env.unwrapped
        throws = base.task_spec.throws
        if throws == 0:  # no wound to guard
            return np.array(v_nominal, dtype=np.float64)
        ready = throws == 1 or bool(base.needle_in_throw_grasp)
        dt = float(base.control_dt)
        result = self._guard.filter_velocity(needle_tip_pos, v_nominal, self.wound(), True, ready, dt)
        x = np.asarray(needle_tip_pos, dtype=np.float64)
        self._record = (
            result.active,
            result.guarding,
            result.mode,
            result.v_nominal,
            result.v_safe,
            result.intervened,
            result.motion_exceeded,
        )
        self._segment = (x, x + result.v_safe * dt, result.filter_time) if result.guarding else None
        return result.v_safe.copy()

    def _update_phase(self, info: dict[str, Any]) -> None:
        base = self.env.unwrapped
        self._guard.observe(bool(info.get("needle_grasped", base.needle_grasped)), int(base.throw_index))

    def _cbf_info(self, info: dict[str, Any]) -> dict[str, Any]:
        tip = info.get("needle_tip_pos", self.env.unwrapped.needle_tip_pos)
        center, axes, rotation = self.safe_set()
        tip = np.asarray(tip, dtype=np.float64)
        record = self._record or (False, False, "", _NAN3, _NAN3, False, False)
        active, guarding, mode, v_nominal, v_safe, intervened, motion_exceeded = record
        tracking = deviation = filter_time = float("nan")
        if self._segment is not None:
            start, end, filter_time = self._segment
            tracking = float(np.linalg.norm(tip - end))
            points = info.get("needle_tip_trace", tip[None])
            deviation = float(np.max(segment_distance(points, start, end)))
        return {
            "cbf_active": active,
            "cbf_guarding": guarding,
            "cbf_mode": mode,
            "h": float(ellipsoid_h(tip, center, axes, rotation)),
            "v_nominal": v_nominal.copy(),
            "v_safe": v_safe.copy(),
            "cbf_intervened": intervened,
            "cbf_tracking_error": tracking,
            "cbf_segment_deviation": deviation,
            "cbf_filter_time": filter_time,
            "cbf_motion_exceeded": motion_exceeded,
        }

    def reset(self, **kwargs):
        self._guard.reset()
        self._record = None
        self._segment = None
        obs, info = self.env.reset(**kwargs)
        info = dict(info)
        info.update(self._cbf_info(info))
        return obs, info

    def step(self, action):
        self._record = None
        self._segment = None
        obs, reward, terminated, truncated, info = self.env.step(action)
        info = dict(info)
        info.update(self._cbf_info(info))
        self._update_phase(info)
        return obs, reward, terminated, truncated, info

    def close(self):
        base = self.env.unwrapped
        if getattr(base, "tip_velocity_filter", None) == self._filter_tip_velocity:
            base.tip_velocity_filter = None
        super().close()
