"""The recorded dataset's layout: LeRobot feature keys, shapes and names, its fps and its task string.

``record``'s module docstring has the table of features; ``dataset_features`` is what
``LeRobotDataset.create`` receives.
"""

from __future__ import annotations

from lerobot_suture.sim import task
from lerobot_suture.sim.regrasp_target import REGRASP_TARGET_NAMES
from lerobot_suture.sim.relative_actions import RELATIVE_ACTION_NAMES
from lerobot_suture.sim.subtasks import SUBTASK_NAMES
from lerobot_suture.sim.wound_marks import MARKS_NAMES

TASK = task.TASK
"""The task string of every frame (LeRobot's ``task``)."""
ROBOT_TYPE = "psm"
FPS = round(1.0 / task.CONTROL_DT)
"""Dataset fps: the env's control rate (10 Hz)."""

IMAGE_KEY = "observation.images.endoscope"
WRIST_IMAGE_KEY = "observation.images.wrist"
"""The wrist camera's image, in datasets recorded with ``--wrist_camera=true``."""
STATE_KEY = "observation.state"
ENV_STATE_KEY = "observation.environment_state"
NEEDLE_KEYPOINTS_KEY = "observation.needle_keypoints"
PRIVILEGED_FEATURES = (NEEDLE_KEYPOINTS_KEY,)
"""Training targets only a simulator knows. LeRobot makes every ``observation.*`` key of a dataset a policy
input, so a default ``lerobot-train`` run lists them among its inputs; no env or real system gives them."""
ACTION_KEY = "action"
REWARD_KEY = "next.reward"
SUCCESS_KEY = "next.success"
DONE_KEY = "next.done"

POSE_NAMES = ["x", "y", "z", "r11", "r21", "r31", "r12", "r22", "r32", "jaw"]
"""Jaw-tip pose: position (m), first two columns of the rotation matrix, jaw closure (1 = closed)."""
ENV_STATE_NAMES = (
    [f"entry_{a}" for a in "xyz"]
    + [f"exit_{a}" for a in "xyz"]
    + [f"needle_centre_{a}" for a in "xyz"]
    + ["needle_r11", "needle_r21", "needle_r31", "needle_r12", "needle_r22", "needle_r32"]
    + [f"needle_tip_{a}" for a in "xyz"]
)
NEEDLE_KEYPOINT_NAMES = [f"{point}_{axis}" for point in ("tip", "middle", "tail") for axis in "xy"]
"""The needle in the endoscope image: normalized x (right) and y (down) of its tip, middle and tail."""


def dataset_features(
    obs_type: str,
    image_size: int,
    video: bool,
    wrist_camera: bool = False,
    marks: bool = False,
    subtask: bool = False,
    relative_actions: bool = False,
    regrasp_target: bool = False,
) -> dict[str, dict]:
    """LeRobot feature specification of the dataset (``LeRobotDataset.create(features=...)``); ``marks``: the
    wound's marks as ``observation.environment_state`` (6,), in place of the privileged one; ``subtask``: the
    high level's subtask and throw (5,) there too, after the marks; ``relative_actions``: the action as the
    motion from the jaw's measured pose, named by :data:`RELATIVE_ACTION_NAMES`; ``regrasp_target``: the
    regrasp planned through the marks, in the jaw frame (9,), after the marks and the subtask."""
    features: dict[str, dict] = {}
    if "pixels" in obs_type:
        image = {
            "dtype": "video" if video else "image",
            "shape": (image_size, image_size, 3),
            "names": ["height", "width", "channels"],
        }
        features[IMAGE_KEY] = image
        if wrist_camera:
            features[WRIST_IMAGE_KEY] = dict(image)
        features[NEEDLE_KEYPOINTS_KEY] = {
            "dtype": "float32",
            "shape": (len(NEEDLE_KEYPOINT_NAMES),),
            "names": NEEDLE_KEYPOINT_NAMES,
        }
    features[STATE_KEY] = {"dtype": "float32", "shape": (10,), "names": list(POSE_NAMES)}
    if obs_type in ("state", "pixels_agent_pos_state"):
        features[ENV_STATE_KEY] = {"dtype": "float32", "shape": (18,), "names": list(ENV_STATE_NAMES)}
    registered = (
        (list(MARKS_NAMES) if marks else [])
        + (list(SUBTASK_NAMES) if subtask else [])
        + (list(REGRASP_TARGET_NAMES) if regrasp_target else [])
    )
    if registered:
        features[ENV_STATE_KEY] = {"dtype": "float32", "shape": (len(registered),), "names": registered}
    action_names = RELATIVE_ACTION_NAMES if relative_actions else POSE_NAMES
    features[ACTION_KEY] = {"dtype": "float32", "shape": (10,), "names": list(action_names)}
    features[REWARD_KEY] = {"dtype": "float32", "shape": (1,), "names": None}
    features[SUCCESS_KEY] = {"dtype": "bool", "shape": (1,), "names": None}
    features[DONE_KEY] = {"dtype": "bool", "shape": (1,), "names": None}
    return features
