"""The needle-insertion task in numbers: the instruction, the control rate, the workspace, how each
episode's phantom and grasp are drawn, and the tolerances of a successful insertion.

``suture_env.SutureEnv`` simulates the task; the dataset recorder, its card and the experiments read these
numbers from here.
"""

import math

import numpy as np

TASK = "Insert the curved suture needle at the entry point and drive it out through the exit point."
"""The task string of the dataset's frames and of policy inputs."""
CONTROL_DT = 0.1
"""Control period (s): 10 Hz, the dataset's fps."""
APPROACH_SPEED = 0.02
"""Speed of the scripted motions' approaches (m/s): the expert's (the needle's centre) and the regrasp servo's."""
DESCEND_SPEED = 0.01
"""Speed of the scripted motions' last approach onto a target (m/s): the expert's and the regrasp servo's."""
TURN_RATE = 0.8
"""Largest turn rate of the scripted approaches (rad/s): the expert's and the regrasp servo's."""
DRIVE_RATE = 0.6
"""Turn rate of the needle about its centre when the scripted motions drive or pull it (rad/s)."""
POSITION_TOLERANCE = 0.0005
"""Distance to a scripted waypoint that counts as reached (m)."""
ANGLE_TOLERANCE = 0.03
"""Turn left to a scripted waypoint's heading that counts as reached (rad)."""

# Workspace of the jaw tip (m, world): the action-space bounds of the position.
WORKSPACE_LOW = np.array([-0.05, -0.06, 0.0])
WORKSPACE_HIGH = np.array([0.05, 0.04, 0.08])

# Phantom placement (m, rad): nominal pose of the top-surface centre, and the training range.
PHANTOM_NOMINAL = np.array([0.0, 0.0, 0.01])
PHANTOM_RANGE_XY = 0.010
PHANTOM_YAW_RANGE = 0.25

# Grasp (rad, m): the jaw holds the needle near its tail; the expert reads the true grasp.
GRASP_ANGLE = math.radians(165.0)
GRASP_ANGLE_RANGE = math.radians(4.0)
GRASP_OFFSET_RANGE = 0.0005
GRASP_ROLL_RANGE = 0.05
GRASP_RANGES = {
    "narrow": (GRASP_ANGLE_RANGE, GRASP_OFFSET_RANGE, GRASP_ROLL_RANGE),
    "wide": (math.radians(12.0), 0.001, 0.10),
}
"""Half-ranges of the grasp's randomization (angle rad, offset along the jaw m, roll rad) by name. "narrow"
is every scene the policy is tested in; "wide" (which contains it) records demonstrations in which the
needle's pose in the jaw changes the action enough that a policy must read it from the image."""
ARM_START_NOISE = np.array([0.03, 0.03, 0.002, 0.05, 0.03, 0.03])
"""Half-range of the uniform noise on the arm's start joints (rad; m for insertion), in the order
outer yaw, outer pitch, insertion, instrument roll, wrist pitch, wrist yaw."""
NEEDLE_TILT = math.radians(30.0)
"""Tilt of the needle's plane from the tissue normal during a throw, towards the arm's port."""

# Success (m): in the manner of the Surgical Robotics Challenge's needle-insertion scoring.
ENTRY_TOLERANCE = 0.002
EXIT_TOLERANCE = 0.002
MIN_PROTRUSION = 0.003
