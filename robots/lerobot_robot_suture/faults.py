"""Fault injection on the robot path: what a real endoscope and a real arm do wrong.

Every fault is off by default; each models one failure of a real da Vinci-style setup. Times are in
control steps of 0.1 s (the robot's 10 Hz loop); a scene's control step ``k`` is its ``k``-th observation
(0-based, the reset observation is step 0).

- ``frozen_camera_step``: the endoscope's video pipeline hangs (a stuck frame grabber, a frozen capture
  card): from that step on the camera delivers the frame of that step, while the pose keeps updating.
- ``dropped_frame_rate``: the camera misses frames (a lossy link, a busy USB bus): per observation, with
  that probability, it delivers no new frame and the previous frame is delivered again.
- ``observation_latency``: the whole measurement (pose and image) reaches the controller that many steps
  late (a slow transport, a buffered video stream). At the start of a scene the oldest measurement there
  is, the reset observation, stands in.
- ``command_latency``: the arm executes the command sent that many steps earlier (a queued command link);
  until that many commands have been sent in a scene it holds its measured pose.
- ``arm_lag``: the arm's servo is sluggish: per step it goes only ``1 - arm_lag`` of the way from its
  measured pose to the commanded target (position in m, jaw closure in [0, 1], the two rotation columns
  interpolated entry by entry).

``FaultInjector`` applies them: ``observe`` to each observation the robot returns, ``command`` to each
target pose before the arm executes it. Numpy only.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

POSE_KEYS = (
    "x.pos",
    "y.pos",
    "z.pos",
    "r11.pos",
    "r21.pos",
    "r31.pos",
    "r12.pos",
    "r22.pos",
    "r32.pos",
    "jaw.pos",
)
"""The pose's scalar feature names in the robot's order (``config_suture_sim.POSE_FEATURES``): position (m),
the first two columns of the rotation matrix, jaw closure."""
MAX_LATENCY_STEPS = 10
_PARALLEL_CROSS = 1e-3  # |c1 x c2| below this: the interpolated columns no longer define a rotation


@dataclass
class FaultConfig:
    """Faults injected on the robot path; every one off by default.

    Args:
        frozen_camera_step: from this control step of a scene on (0-based count of observations since the
            scene's reset), the camera delivers the frame it delivered at that step. None: never.
        dropped_frame_rate: per observation, the probability that the camera delivers no new frame (the
            previous delivered frame is delivered again), in [0, 1).
        observation_latency: the observation returned (pose and image) is the one measured this many
            control steps (0.1 s each) ago, in [0, 10].
        command_latency: the arm executes the action sent this many control steps earlier, in [0, 10];
            until that many have been sent in a scene it holds its measured pose.
        arm_lag: the share of the way from its measured pose to the commanded target the arm does not go
            per step, in [0, 1).
        seed: seed of the frame drops; a scene's drops come from ``np.random.default_rng([seed,
            scene_seed])``.
    """

    frozen_camera_step: int | None = None
    dropped_frame_rate: float = 0.0
    observation_latency: int = 0
    command_latency: int = 0
    arm_lag: float = 0.0
    seed: int = 0

    def __post_init__(self):
        if self.frozen_camera_step is not None and self.frozen_camera_step < 0:
            raise ValueError(f"`frozen_camera_step` must be None or >= 0. Got {self.frozen_camera_step}.")
        if not 0.0 <= self.dropped_frame_rate < 1.0:
            raise ValueError(f"`dropped_frame_rate` must be in [0, 1). Got {self.dropped_frame_rate}.")
        for name in ("observation_latency", "command_latency"):
            value = getattr(self, name)
            if not 0 <= value <= MAX_LATENCY_STEPS:
                raise ValueError(f"`{name}` must be in [0, {MAX_LATENCY_STEPS}]. Got {value}.")
        if not 0.0 <= self.arm_lag < 1.0:
            raise ValueError(f"`arm_lag` must be in [0, 1). Got {self.arm_lag}.")
        if self.seed < 0:
            raise ValueError(f"`seed` must be >= 0. Got {self.seed}.")

    @property
    def any(self) -> bool:
        """True when some fault is on."""
        return (
            self.frozen_camera_step is not None
            or self.dropped_frame_rate > 0.0
            or self.observation_latency > 0
            or self.command_latency > 0
            or self.arm_lag > 0.0
        )


class FaultInjector:
    """Applies a ``FaultConfig`` to a robot's observations and commands, scene by scene.

    Call ``reset(scene_seed)`` at each scene's start (construction resets to scene seed 0), ``observe`` on
    each observation in order, and ``command`` on each target pose.

    Args:
        config: the faults.
        camera_key: the observation's image entry.
        pose_keys: the observation's 10 pose entries, delayed with the image by ``observation_latency``.
        derived_keys: entries computed from the measured pose (the planned regrasp, seen from it), delayed
            with it so that the two still agree.
    """

    def __init__(
        self,
        config: FaultConfig,
        camera_key: str = "endoscope",
        pose_keys: Sequence[str] = POSE_KEYS,
        derived_keys: Sequence[str] = (),
    ):
        if len(pose_keys) != len(POSE_KEYS):
            raise ValueError(f"`pose_keys` must name {len(POSE_KEYS)} pose entries. Got {len(pose_keys)}.")
        self.config = config
        self.camera_key = camera_key
        self.pose_keys = tuple(pose_keys)
        self.delayed_keys = (*pose_keys, *derived_keys)
        self.reset(0)

    def reset(self, scene_seed: int) -> None:
        """Start a scene: clear the buffers, the frozen and last frames, and reseed the drops."""
        self.scene_seed = int(scene_seed)
        self.step = 0  # observations seen in this scene
        self._rng = np.random.default_rng([self.config.seed, self.scene_seed])
        self._frozen: np.ndarray | None = None
        self._last_frame: np.ndarray | None = None
        self._dropped: list[int] = []
        self._observations: deque[dict] = deque(maxlen=self.config.observation_latency + 1)
        self._commands: deque[np.ndarray] = deque(maxlen=self.config.command_latency + 1)

    @property
    def dropped_steps(self) -> tuple[int, ...]:
        """The control steps of this scene whose frame was dropped (the previous one delivered again)."""
        return tuple(self._dropped)

    def observe(self, observation: dict) -> dict:
        """The observation the controller receives, given the one the robot measured now.

        Args:
            observation: ``{camera_key: (H, W, 3) uint8, "x.pos": float, ...}``; not mutated.

        Returns:
            A new dict with the camera faults, then the observation latency (on the image, the
            ``pose_keys`` and the ``derived_keys``), applied; other entries pass through. Its frame is a copy
            whenever a fault is on.
        """
        step = self.step
        self.step += 1
        if not self.config.any:
            return dict(observation)
        measured = {key: observation[key] for key in self.delayed_keys}
        measured[self.camera_key] = self._camera(np.asarray(observation[self.camera_key]), step)
        self._observations.append(measured)
        # The deque holds the last latency + 1 measurements: its oldest is the one latency steps ago, or
        # the reset observation while fewer have come.
        out = dict(observation)
        out.update(self._observations[0])
        out[self.camera_key] = out[self.camera_key].copy()
        return out

    def _camera(self, frame: np.ndarray, step: int) -> np.ndarray:
        """The frame the camera delivers at ``step`` (a stored copy), given the one it captured."""
        config = self.config
        # Drawn on every step, so a scene's drops do not depend on the other faults.
        dropped = config.dropped_frame_rate > 0.0 and self._rng.random() < config.dropped_frame_rate
        if self._frozen is not None:
            delivered = self._frozen
        elif dropped and self._last_frame is not None:
            self._dropped.append(step)
            delivered = self._last_frame
        else:
            delivered = frame.copy()
        if config.frozen_camera_step is not None and step == config.frozen_camera_step:
            self._frozen = delivered
        self._last_frame = delivered
        return delivered

    def command(self, target: np.ndarray, measured_pose: np.ndarray) -> np.ndarray:
        """The pose the arm executes now, given the target sent now and its measured pose.

        Args:
            target: (10,) commanded pose (m, rotation columns, jaw closure).
            measured_pose: (10,) the arm's measured pose, same layout.

        Returns:
            (10,) float64: the command latency's delayed target (or the measured pose while the queue
            fills), then moved only ``1 - arm_lag`` of the way from the measured pose.
        """
        target = np.asarray(target, dtype=np.float64)
        measured = np.asarray(measured_pose, dtype=np.float64)
        if target.shape != (10,) or measured.shape != (10,):
            raise ValueError(
                f"`target` and `measured_pose` must have shape (10,). Got {target.shape} and {measured.shape}."
            )
        self._commands.append(target.copy())
        if len(self._commands) < self._commands.maxlen:
            executed = measured.copy()
        else:
            executed = self._commands[0].copy()
        if self.config.arm_lag == 0.0:
            return executed
        return _lagged(measured, executed, 1.0 - self.config.arm_lag)


def _lagged(measured: np.ndarray, target: np.ndarray, share: float) -> np.ndarray:
    """(10,) pose ``share`` of the way from ``measured`` to ``target``, entry by entry; the target's rotation
    columns where the interpolated ones are near-parallel (opposite rotations)."""
    out = measured + share * (target - measured)
    if np.linalg.norm(np.cross(out[3:6], out[6:9])) < _PARALLEL_CROSS:
        out[3:9] = target[3:9]
    return out
