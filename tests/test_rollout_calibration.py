"""``lerobot-suture calibrate --rollouts``: the ensemble's gate fitted on rollouts recorded by
``lerobot-rollout --strategy.type=gated_dagger``, as a gate deployed under real-time chunking is calibrated."""

import json
import math
import shutil

import numpy as np
import pytest
from robot_commands import dataset_args, episode_frames, load_dataset, robot_args, run_command

from lerobot_suture.runtime.rollout_calibration import check_bounds_do_not_decide, episode_predictions
from lerobot_suture.safety.ood.calibration import conformal_episode_threshold

NAN = math.nan


def test_a_prediction_is_a_change_of_the_score_and_the_surgeon_s_frames_are_left_out():
    episode = np.array([3, 3, 3, 3, 3, 5, 5, 5, 5, 5])
    score = np.array([NAN, 1.0, 1.0, 2.0, 1.0, 0.5, 0.5, 4.0, 4.0, 9.0])
    intervention = np.array([0, 0, 0, 0, 0, 0, 0, 1, 1, 1])
    scores, ids, handed_over = episode_predictions(episode, score, intervention)
    # Episode 3: 1, 2, then 1 again (a new prediction); episode 5: 0.5, and 4.0 on the handover frame, which
    # carries the score that handed over; the surgeon's 9.0 is not the policy's.
    np.testing.assert_array_equal(scores, [1.0, 2.0, 1.0, 0.5, 4.0])
    np.testing.assert_array_equal(ids, [0, 0, 0, 1, 1])
    np.testing.assert_array_equal(handed_over, [False, True])


def test_a_handed_over_episode_may_not_decide_the_threshold():
    maxima = np.linspace(1.0, 2.0, 20)
    threshold = conformal_episode_threshold(maxima, 0.05)
    above = maxima > threshold
    assert check_bounds_do_not_decide(maxima, above, 0.05) == threshold  # bounds above it: it holds
    at = maxima == threshold
    with pytest.raises(
        ValueError, match="1 of the 20 episodes were handed over.*--policy.ood.calibration_file"
    ):
        check_bounds_do_not_decide(maxima, at, 0.05)


def test_a_dataset_without_the_gate_s_labels_is_refused(tmp_path):
    from lerobot_suture.runtime.rollout_calibration import recorded_frames

    with pytest.raises(FileNotFoundError, match="gated_dagger"):
        recorded_frames(tmp_path)
    (tmp_path / "data" / "chunk-000").mkdir(parents=True)
    import pandas as pd

    pd.DataFrame({"episode_index": [0], "index": [0]}).to_parquet(
        tmp_path / "data" / "chunk-000" / "file-000.parquet"
    )
    with pytest.raises(ValueError, match=r"no \['ood_score', 'intervention'\].*gated_dagger"):
        recorded_frames(tmp_path)


def test_the_rollout_flags_refuse_what_they_cannot_do(tiny_policy_dir, tmp_path):
    from lerobot_suture.runtime.calibration import CalibrateConfig
    from lerobot_suture.runtime.config import PolicyPathConfig

    policy = PolicyPathConfig(path=tiny_policy_dir)
    with pytest.raises(ValueError, match="drop `per_stage`"):
        CalibrateConfig(policy=policy, rollouts=tmp_path, per_stage=True, workers=1)
    with pytest.raises(ValueError, match="plain .json file name"):
        CalibrateConfig(policy=policy, calibration_file="../elsewhere.json")


@pytest.mark.slow
@pytest.mark.parametrize("engine", ["sync", "rtc"])
def test_an_uncalibrated_policy_s_rollouts_calibrate_its_gate(tiny_policy_dir, tmp_path, engine):
    """Recorded with the calibration file about to be written absent, the gate reports every score and never
    hands over; ``calibrate --rollouts`` then writes that file, with the conformal quantile of the episodes'
    largest scores (read here through LeRobot's own dataset), and the policy reads it by name."""
    policy = tmp_path / "policy"
    shutil.copytree(tiny_policy_dir, policy)
    root, name = tmp_path / "rollouts", "ood_calibration_rtc.json"
    log = run_command(
        "lerobot-rollout",
        [
            "--strategy.type=gated_dagger",
            f"--policy.path={policy}",
            f"--policy.ood.calibration_file={name}",
            "--teleop.type=suture_scripted",
            "--device=cpu",
            "--fps=20",
            "--return_to_initial_position=false",
            f"--inference.type={engine}",
            *robot_args(tmp_path / "trace.jsonl", "--robot.seed=11", "--robot.clock=fast"),
            *dataset_args(root, "local/rollout_calibration", episodes=4, episode_s=1.5, reset_s=0),
        ],
        timeout=600,
    )
    assert "gate ensemble, uncalibrated (reports scores only)" in log
    dataset = load_dataset(root, "local/rollout_calibration")
    maxima = []
    for episode in range(dataset.meta.total_episodes):
        frames = episode_frames(dataset, episode)
        assert not any(bool(f["intervention"]) for f in frames)
        scores = np.array([float(f["ood_score"]) for f in frames])
        assert np.isfinite(scores).any()
        maxima.append(np.nanmax(scores))
    run_command(
        "lerobot-suture",
        [
            "calibrate",
            f"--policy.path={policy}",
            f"--rollouts={root}",
            f"--calibration_file={name}",
            "--alpha=0.2",
        ],
    )
    fitted = json.loads((policy / name).read_text())
    assert fitted["mode"] == "per_episode"
    assert fitted["threshold"] == pytest.approx(conformal_episode_threshold(np.array(maxima), 0.2), rel=1e-6)
    report = json.loads((policy / "ood_calibration_rtc_report.json").read_text())
    assert (report["episodes"], report["rtc_score"]) == (len(maxima), "inpainted")
    assert not (policy / "ood_calibration.json").exists()  # the policy's own calibration file is not touched

    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class

    config = PreTrainedConfig.from_pretrained(policy)
    config.ood.calibration_file, config.ood.enforce = name, True  # --policy.ood.calibration_file=NAME
    loaded = get_policy_class(config.type).from_pretrained(policy, config=config)
    assert loaded.ood_calibration.threshold == pytest.approx(fitted["threshold"])


def test_episodes_without_a_score_are_refused(tmp_path):
    """An episode recorded with `--strategy.gate=none`, or by a policy without a gate, has no score to fit."""
    import pandas as pd

    from lerobot_suture.runtime.rollout_calibration import rollout_scores

    (tmp_path / "data" / "chunk-000").mkdir(parents=True)
    pd.DataFrame(
        {
            "index": [0, 1, 2, 3],
            "episode_index": [0, 0, 1, 1],
            "ood_score": [[NAN], [NAN], [0.1], [0.2]],
            "intervention": [False] * 4,
        }
    ).to_parquet(tmp_path / "data" / "chunk-000" / "file-000.parquet")
    with pytest.raises(ValueError, match="1 of the 2 episodes .* carry no gate score.*--strategy.gate=none"):
        rollout_scores(tmp_path, "per_episode", 0.05)
