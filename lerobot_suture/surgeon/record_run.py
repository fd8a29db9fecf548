"""A policy run with a surgeon, recorded as a LeRobotDataset: the demonstrations' features plus who acted.

The frames carry the demonstrations' features (``datasets/features.py``: endoscope image, state,
needle keypoints, action, reward, success, done) and four labels, under LeRobot's HIL prefix
``complementary_info.`` (LeRobot's ``ReplayBuffer.from_lerobot_dataset`` reads every key with it back as a
transition's complementary info, and its HIL actor stores ``is_intervention`` there):

======================================== ======= ===============================================
key                                      dtype   meaning
======================================== ======= ===============================================
``complementary_info.is_intervention``   float32 1 when the surgeon's action replaced the policy's
``complementary_info.actor``             int64   0 policy, 1 surgeon, 2 hold (``takeover.Actor``)
``complementary_info.uncertainty_score`` float32 the gate's score of the prediction in force; NaN
                                                 when the policy was not consulted at that step
``complementary_info.gate_decision``     int64   1 out of distribution, 0 in, -1 not consulted
======================================== ======= ===============================================

``is_intervention`` is float32 because that is how LeRobot's own HIL datasets store it (its replay
buffer writes complementary info as float32). :func:`label_demonstrations` adds the same four columns to
a demonstration dataset (actor surgeon, no intervention, no policy), so LeRobot's ``merge_datasets``
(which needs equal features) can join the two.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lerobot_suture.datasets.features import (
    ACTION_KEY,
    DONE_KEY,
    ENV_STATE_KEY,
    FPS,
    IMAGE_KEY,
    NEEDLE_KEYPOINTS_KEY,
    REWARD_KEY,
    ROBOT_TYPE,
    STATE_KEY,
    SUCCESS_KEY,
    TASK,
    dataset_features,
)
from lerobot_suture.datasets.scheduling import normal_scheduling
from lerobot_suture.runtime.takeover import Actor

IS_INTERVENTION_KEY = "complementary_info.is_intervention"
ACTOR_KEY = "complementary_info.actor"
UNCERTAINTY_KEY = "complementary_info.uncertainty_score"
GATE_DECISION_KEY = "complementary_info.gate_decision"
NOT_CONSULTED = -1

LABEL_FEATURES = {
    IS_INTERVENTION_KEY: {"dtype": "float32", "shape": (1,), "names": None},
    ACTOR_KEY: {"dtype": "int64", "shape": (1,), "names": None},
    UNCERTAINTY_KEY: {"dtype": "float32", "shape": (1,), "names": None},
    GATE_DECISION_KEY: {"dtype": "int64", "shape": (1,), "names": None},
}


def run_features(obs_type: str, image_size: int, video: bool) -> dict[str, dict]:
    """The recorded run's LeRobot features: the demonstrations' plus :data:`LABEL_FEATURES`."""
    return {**dataset_features(obs_type, image_size, video), **LABEL_FEATURES}


def labels(actor: Actor, score: float, decision: int) -> dict[str, np.ndarray]:
    """One frame's label columns."""
    return {
        IS_INTERVENTION_KEY: np.array([float(actor is Actor.SURGEON)], dtype=np.float32),
        ACTOR_KEY: np.array([int(actor)], dtype=np.int64),
        UNCERTAINTY_KEY: np.array([score], dtype=np.float32),
        GATE_DECISION_KEY: np.array([int(decision)], dtype=np.int64),
    }


class RunRecorder:
    """Records each control step of a surgeon run with LeRobot's own writer (``LeRobotDataset.create``).

    Args:
        repo_id: dataset id (``user/name``); local unless pushed.
        root: new directory of the dataset (must not exist).
        obs_type, image_size: the env's observation settings (the policy's).
        video: store the endoscope as MP4 (true, as the demonstrations by default) or PNG frames.
    """

    def __init__(self, repo_id: str, root: str | Path, obs_type: str, image_size: int, video: bool = True):
        from lerobot.datasets.lerobot_dataset import LeRobotDataset

        from lerobot_suture.datasets.video import resolve_video_backend

        self._keypoints = None
        self.dataset = LeRobotDataset.create(
            repo_id,
            FPS,
            run_features(obs_type, image_size, video),
            root=root,
            robot_type=ROBOT_TYPE,
            use_videos=video,
            video_backend=resolve_video_backend() if video and "pixels" in obs_type else "pyav",
        )

    def add(self, env, observation: dict, action, reward, info, done, actor, score, decision) -> None:
        """One frame: the observation the step acted on, the executed action, what the step returned."""
        frame = {
            STATE_KEY: np.asarray(observation["agent_pos"], dtype=np.float32),
            ACTION_KEY: np.asarray(action, dtype=np.float32),
            REWARD_KEY: np.array([reward], dtype=np.float32),
            SUCCESS_KEY: np.array([bool(info["is_success"])]),
            DONE_KEY: np.array([bool(done)]),
            "task": TASK,
            **labels(actor, score, decision),
        }
        if "pixels" in observation:
            frame[IMAGE_KEY] = observation["pixels"]["endoscope"]
        if "environment_state" in observation:
            frame[ENV_STATE_KEY] = np.asarray(observation["environment_state"], dtype=np.float32)
        if IMAGE_KEY in frame:
            frame[NEEDLE_KEYPOINTS_KEY] = self._keypoints
        self.dataset.add_frame(frame)

    def observe(self, env) -> None:
        """Locate the needle in the image of the observation about to be acted on (the demos' target)."""
        self._keypoints = np.asarray(env.unwrapped.needle_keypoints_in_image(), dtype=np.float32)

    def save_episode(self) -> None:
        with normal_scheduling():  # the video encoder may leave the thread real-time
            self.dataset.save_episode()

    def finalize(self) -> None:
        with normal_scheduling():
            self.dataset.finalize()


def label_demonstrations(dataset, output_dir: str | Path, repo_id: str):
    """A copy of a demonstration ``LeRobotDataset`` with the run labels (LeRobot's ``add_features``).

    Demonstrations are the scripted expert's, the surgeon stand-in, with no policy running: actor
    surgeon, no intervention (no policy action was replaced), score NaN, gate not consulted.
    """
    from lerobot.datasets.dataset_tools import add_features

    n = dataset.meta.total_frames
    columns = {
        IS_INTERVENTION_KEY: np.zeros((n, 1), dtype=np.float32),
        ACTOR_KEY: np.full((n, 1), int(Actor.SURGEON), dtype=np.int64),
        UNCERTAINTY_KEY: np.full((n, 1), np.nan, dtype=np.float32),
        GATE_DECISION_KEY: np.full((n, 1), NOT_CONSULTED, dtype=np.int64),
    }
    with normal_scheduling():  # copying the videos may start the encoder, which leaves the thread real-time
        return add_features(
            dataset,
            {key: (values, LABEL_FEATURES[key]) for key, values in columns.items()},
            output_dir=output_dir,
            repo_id=repo_id,
        )
