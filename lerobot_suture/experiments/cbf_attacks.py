"""Adversarial attack families on the CBF safety filter: what an attacker commands, step by step.

One set of families serves both paths (``experiments.attack_episodes`` runs them on the env path and, through
the robot plugin's adapter, on the robot path). Each family's commands read only the scene's pose of the jaw
(and the phantom's normal, for ``reenter``); every random choice comes from the episode's generator.

Families (``FAMILIES``); ``hold`` is the jaw position when the attack begins:

============== ==========================================================================================
family         action every control step
============== ==========================================================================================
rotation       the jaw kept where it is (``hold``, or its current position in half the episodes), a
               uniformly random jaw orientation: the rotation-heavy attack that once left the set
spin           ``hold``, the jaw turned by nearly pi about one random axis per episode: the largest
               steady angular velocity the controller commands
push           ``hold`` plus up to 4 cm in a random direction, orientation kept (the sideways pull, in
               every direction)
rotation_push  a push and a random orientation together
oscillation    ``hold`` plus a sinusoid along a random direction (up to 2 cm, 1-5 Hz: bang-bang at the
               10 Hz control rate) and an oscillating turn about a random axis (up to 1.5 rad)
jaw            a chattering jaw closure in [0, 1] (below 0.5 releases the needle: the guarantee ends
               there) with small random pushes and turns
uniform        uniformly random actions over the whole action space
far            targets 0.1-10 m away in a random direction and wild rotation columns: commands far
               outside the workspace (the env clips them to the action space)
reenter        pull the needle back out of the entry (8 mm up), move 3-12 mm sideways along the surface, and
               push 12 mm down: a second entry beside the wound
jaw_ambiguous  a jaw command in [0.5, 0.6] (the needle stays in a jaw that reads far from closed), with one
               in [0.4, 0.5) now and then (let go, then caught again), and pushes and turns
============== ==========================================================================================

The off-distribution policy family is in ``attack_episodes.run_policy_attack`` (it needs torch and a policy).
"""

from __future__ import annotations

import math

import numpy as np

from lerobot_suture.sim.geometry import matrix_from_rotvec, pose_vector, rot6_from_matrix

FAMILIES = (
    "rotation",
    "spin",
    "push",
    "rotation_push",
    "oscillation",
    "jaw",
    "uniform",
    "far",
    "reenter",
    "jaw_ambiguous",
)
"""The scripted attack families; ``policy`` (an ensemble off distribution) is run separately."""
POLICY_FAMILY = "policy"


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random rotation matrix (3, 3) (a normalized Gaussian quaternion)."""
    q = rng.standard_normal(4)
    w, x, y, z = q / max(float(np.linalg.norm(q)), 1e-12)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def random_direction(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random unit vector (3,)."""
    v = rng.standard_normal(3)
    return v / max(float(np.linalg.norm(v)), 1e-12)


class Attacker:
    """One attack family's commands: ``act(env, k)`` gives the (10,) action of attack step ``k``.

    Args:
        family: one of ``FAMILIES``.
        rng: the episode's generator; every random choice of the attack comes from it.
    """

    def __init__(self, family: str, rng: np.random.Generator):
        if family not in FAMILIES:
            raise ValueError(f"`family` must be one of {FAMILIES}. Got {family!r}.")
        self.family = family
        self.rng = rng
        self.hold_pos: np.ndarray | None = None
        self.hold_rot: np.ndarray | None = None
        # Per-episode parameters, drawn once.
        self.follow = bool(rng.integers(2))  # rotation: keep the current position rather than ``hold``
        self.axis = random_direction(rng)
        self.direction = random_direction(rng)
        self.turn_axis = random_direction(rng)
        self.amplitude = rng.uniform(0.002, 0.02)  # m
        self.turn_amplitude = rng.uniform(0.2, 1.5)  # rad
        self.frequency = rng.uniform(1.0, 5.0)  # Hz
        self.sideways = rng.uniform(0.003, 0.012)  # m, reenter

    def begin(self, env) -> None:
        self.hold_pos, self.hold_rot = env.unwrapped.jaw_pose()

    def act(self, env, k: int) -> np.ndarray:
        u, rng = env.unwrapped, self.rng
        pos, rot = u.jaw_pose()
        t = k * u.control_dt
        if self.family == "rotation":
            action = pose_vector(pos if self.follow else self.hold_pos, random_rotation(rng), 1.0)
        elif self.family == "spin":
            action = pose_vector(self.hold_pos, matrix_from_rotvec(0.99 * math.pi * self.axis) @ rot, 1.0)
        elif self.family == "push":
            action = pose_vector(
                self.hold_pos + rng.uniform(0.0, 0.04) * random_direction(rng), self.hold_rot, 1.0
            )
        elif self.family == "rotation_push":
            target = self.hold_pos + rng.uniform(0.0, 0.04) * random_direction(rng)
            action = pose_vector(target, random_rotation(rng), 1.0)
        elif self.family == "oscillation":
            phase = math.sin(2.0 * math.pi * self.frequency * t)
            turn = matrix_from_rotvec(self.turn_amplitude * phase * self.turn_axis)
            action = pose_vector(
                self.hold_pos + self.amplitude * phase * self.direction, turn @ self.hold_rot, 1.0
            )
        elif self.family == "jaw":
            jaw = rng.uniform(0.0, 1.0) if rng.uniform() < 0.15 else rng.uniform(0.5, 1.0)
            target = pos + rng.uniform(0.0, 0.01) * random_direction(rng)
            action = pose_vector(
                target, matrix_from_rotvec(rng.uniform(0.0, 0.5) * random_direction(rng)) @ rot, jaw
            )
        elif self.family == "uniform":
            space = u.action_space
            action = rng.uniform(space.low, space.high)
        elif self.family == "reenter":
            normal = u.phantom_rotation[:, 2]
            sideways = self.direction - (self.direction @ normal) * normal
            sideways *= self.sideways / max(float(np.linalg.norm(sideways)), 1e-12)
            offset = (
                0.008 * normal
                if k < 5
                else 0.008 * normal + sideways
                if k < 10
                else sideways - 0.012 * normal
            )
            action = pose_vector(self.hold_pos + offset, self.hold_rot, 1.0)
        elif self.family == "jaw_ambiguous":
            jaw = rng.uniform(0.4, 0.5) if rng.uniform() < 0.1 else rng.uniform(0.5, 0.6)
            target = pos + rng.uniform(0.0, 0.02) * random_direction(rng)
            action = pose_vector(
                target, matrix_from_rotvec(rng.uniform(0.0, 0.5) * random_direction(rng)) @ rot, jaw
            )
        else:  # far
            target = pos + 10.0 ** rng.uniform(-1.0, 1.0) * random_direction(rng)
            # Huge rotation columns, as the env will clip them to [-1, 1]; clipping can make them parallel,
            # which the env rejects (ValueError, before any motion), so such draws are replaced.
            columns = np.clip(rng.uniform(-1.0, 1.0, 6) * 10.0 ** rng.uniform(0.0, 3.0), -1.0, 1.0)
            if np.linalg.norm(np.cross(columns[:3], columns[3:])) < 1e-3:
                columns = rot6_from_matrix(random_rotation(rng))
            action = np.concatenate([target, columns, [1.0]])
        return np.asarray(action, dtype=np.float32)
