"""The CBF installed at the env step: filters the needle tip's Cartesian velocity inside ``SutureEnv``.

``SutureEnv.step`` turns the action into a Cartesian velocity command for the needle tip, calls
``env.unwrapped.tip_velocity_filter(needle_tip_pos, v_nominal)`` once per control step, and runs
inverse kinematics on the velocity it gets back; the velocity is held for the whole control step
(``control_dt``, 0.1 s) while physics runs at ``physics_dt`` (2 ms). :class:`CBFActionWrapper` sets
that hook. Whatever produced the action (policy, scripted surgeon) is filtered the same way.

Safe set: the ellipsoid of :class:`~lerobot_suture.safety.cbf.CBFConfig`, centred midway between the
phantom's current entry and exit markers, with axes (entry->exit, lateral, tissue normal); it is
rebuilt from the env every control step, so it follows a moving phantom.

Activation (one throw per episode): the filter switches on at the first control step where the
needle is grasped and its tip is inside the set (inside the margin-tightened set in discrete mode,
so the discrete-time guarantee holds from the first step), and switches off for the rest of the
episode when the needle leaves the tissue after having been in it, or is released. ``reset`` starts
over.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from lerobot_suture.safety.cbf import CBFConfig, ellipsoid_h, suture_ellipsoid_frame

PHASE_IDLE = "idle"
"""No throw yet: velocities pass through."""
PHASE_ACTIVE = "active"
"""A throw has begun: velocities are filtered."""
PHASE_DONE = "done"
"""The throw ended (needle out of the tissue, or released): velocities pass through until reset."""

_NAN3 = np.full(3, np.nan)


class CBFActionWrapper(gym.Wrapper):
    """Keeps the needle tip inside the safe ellipsoid around the wound during a suture throw.

    Info keys added to ``reset`` and every ``step``:

    ============== ========== =====================================================================
    key            type       meaning
    ============== ========== =====================================================================
    cbf_active     bool       the filter was applied during this step (phase ``active``)
    h              float      barrier at the needle tip after the step (>= 0 inside the set)
    v_nominal      (3,) m/s   tip velocity the action asked for (NaN if the env did not call the hook)
    v_safe         (3,) m/s   tip velocity sent to the robot (NaN if the env did not call the hook)
    cbf_intervened bool       ``v_safe`` differs from ``v_nominal``
    ============== ========== =====================================================================

    With ``config.enabled`` False the wrapper only monitors: it tracks the phase and reports ``h``
    but sends ``v_nominal`` unchanged (useful as the "filter off" arm of a comparison).

    Args:
        env: an env whose ``unwrapped`` is a ``SutureEnv`` (has ``tip_velocity_filter``,
            ``entry_point``, ``exit_point``, ``phantom_rotation``, ``needle_tip_pos``,
            ``needle_in_tissue``, ``needle_grasped``, ``control_dt``).
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
        self._activation_level = self.config.margin_level if self.config.discrete else 0.0
        self._phase = PHASE_IDLE
        self._seen_in_tissue = False
        self._record: tuple[bool, np.ndarray, np.ndarray, bool] | None = None
        base.tip_velocity_filter = self._filter_tip_velocity

    @property
    def phase(self) -> str:
        """``idle``, ``active`` or ``done`` (see the module docstring)."""
        return self._phase

    def safe_set(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The current safe ellipsoid from the env's entry/exit markers.

        Returns:
            (center (3,) m, semi-axes (3,) m, rotation (3, 3) world-from-ellipsoid).
        """
        base = self.env.unwrapped
        normal = np.asarray(base.phantom_rotation, dtype=np.float64)[:, 2]
        center, rotation = suture_ellipsoid_frame(base.entry_point, base.exit_point, normal)
        return center, self._axes, rotation

    def h_min(self, points: np.ndarray) -> float:
        """Smallest h over ``points`` (N, 3) m in the current safe set, e.g. ``info["needle_tip_trace"]``."""
        center, axes, rotation = self.safe_set()
        return float(np.min(ellipsoid_h(np.asarray(points, dtype=np.float64), center, axes, rotation)))

    def _filter_tip_velocity(self, needle_tip_pos: np.ndarray, v_nominal: np.ndarray) -> np.ndarray:
        """The hook SutureEnv calls: (3,) tip position (m), (3,) nominal velocity (m/s) -> (3,) m/s."""
        base = self.env.unwrapped
        x = np.asarray(needle_tip_pos, dtype=np.float64)
        v = np.array(v_nominal, dtype=np.float64)
        center, axes, rotation = self.safe_set()
        if (
            self._phase == PHASE_IDLE
            and bool(base.needle_grasped)
            and ellipsoid_h(x, center, axes, rotation) >= self._activation_level
        ):
            self._phase = PHASE_ACTIVE
            self._seen_in_tissue = bool(base.needle_in_tissue)
        active = self._phase == PHASE_ACTIVE
        if active and self.config.enabled:
            result = self.config.filter(x, v, center, rotation, float(base.control_dt))
            v_safe, intervened = result.v_safe, result.intervened
        else:
            v_safe, intervened = v.copy(), False
        self._record = (active, v, v_safe, bool(intervened))
        return v_safe.copy()

    def _update_phase(self, info: dict[str, Any]) -> None:
        if self._phase != PHASE_ACTIVE:
            return
        base = self.env.unwrapped
        in_tissue = bool(info.get("needle_in_tissue", base.needle_in_tissue))
        grasped = bool(info.get("needle_grasped", base.needle_grasped))
        if in_tissue:
            self._seen_in_tissue = True
        elif self._seen_in_tissue:
            self._phase = PHASE_DONE
        if not grasped:
            self._phase = PHASE_DONE

    def _cbf_info(self, info: dict[str, Any]) -> dict[str, Any]:
        tip = info.get("needle_tip_pos", self.env.unwrapped.needle_tip_pos)
        center, axes, rotation = self.safe_set()
        active, v_nominal, v_safe, intervened = self._record or (False, _NAN3, _NAN3, False)
        return {
            "cbf_active": active,
            "h": float(ellipsoid_h(np.asarray(tip, dtype=np.float64), center, axes, rotation)),
            "v_nominal": v_nominal.copy(),
            "v_safe": v_safe.copy(),
            "cbf_intervened": intervened,
        }

    def reset(self, **kwargs):
        self._phase = PHASE_IDLE
        self._seen_in_tissue = False
        self._record = None
        obs, info = self.env.reset(**kwargs)
        info = dict(info)
        info.update(self._cbf_info(info))
        return obs, info

    def step(self, action):
        self._record = None
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
