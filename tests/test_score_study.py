"""`lerobot-suture score-study`: every score choice from the same samples, its gate replayed, its metrics."""

import json
import math
import shutil

import gymnasium as gym
import numpy as np
import pytest
import torch
from lerobot_suture_studies.score_study import (
    RescoringRunner,
    ScoreStudyConfig,
    choice_grid,
    choice_label,
    with_scores,
)
from PIL import Image

import lerobot_suture
from lerobot_suture.cli import main as cli_main
from lerobot_suture.runtime.calibration import SCORE_CHOICE_FIELDS
from lerobot_suture.runtime.config import PolicyPathConfig
from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy
from lerobot_suture.runtime.rollout import EpisodeLog, StepLog, rollout_seeds
from lerobot_suture.safety.ood.calibration import fit_calibration
from lerobot_suture.safety.ood.gate import OODGate


def _log(scores, new_prediction, success=True, perturbed_from=None) -> EpisodeLog:
    steps = [
        StepLog(
            s,
            math.nan,
            False,
            False,
            new,
            "policy",
            perturbed_from is not None and k >= perturbed_from,
            False,
        )
        for k, (s, new) in enumerate(zip(scores, new_prediction, strict=True))
    ]
    return EpisodeLog(seed=0, scenario="nominal", success=success, steps=steps)


def test_replayed_gate_decides_at_new_predictions_only_and_latches():
    calibration = fit_calibration(
        np.abs(np.random.default_rng(0).lognormal(0, 0.1, 40)),
        model="lognormal",
        mode="per_episode",
        episode_ids=np.repeat(np.arange(20), 2),
    )
    t = calibration.threshold
    log = _log([0.0] * 6, [True, False, True, False, True, False])
    # Over the threshold on a step without a new prediction: the gate has not seen it yet.
    replayed = with_scores(
        log, np.array([0.5 * t, 2 * t, 2 * t, 0.1 * t, 0.1 * t, 0.1 * t]), OODGate(calibration)
    )
    assert [s.ood for s in replayed.steps] == [False, False, True, True, True, True]
    assert replayed.scores.tolist()[1] == 2 * t
    assert [s.ood for s in log.steps] == [False] * 6  # the original log is left alone


class _StubPolicy:
    """Predicts every 2nd call; the prediction is the call index, its score under choice c is c + index."""

    def __init__(self):
        self.calls, self.last_prediction = 0, None

    def ood_status(self, index):
        return {"new_prediction": self.calls % 2 == 1}

    def rescore(self, prediction, offset):
        return torch.tensor([offset + prediction, 100.0 + offset + prediction])  # two envs


class _StubRunner:
    def __init__(self):
        self.policy = _StubPolicy()
        self.gate = GateMode.REPORT

    def reset(self, seeds=None):
        self.policy.calls = 0

    def act_batch(self, observations, tasks=None):
        if self.policy.calls % 2 == 0:
            self.policy.last_prediction = self.policy.calls
        self.policy.calls += 1
        return np.zeros((len(observations), 10))


def test_rescoring_runner_hands_each_episode_its_rows_held_between_predictions():
    runner = RescoringRunner(_StubRunner(), [{"offset": 0.0}, {"offset": 0.5}])
    for calls in (5, 3):  # two rollout batches: 5 then 3 control steps
        runner.reset()
        for _ in range(calls):
            runner.act_batch([{}, {}])
    logs = [_log([0.0] * n, [True] * n) for n in (5, 2, 3, 1)]  # env 1 of batch 1 ended after 2 steps
    traces = runner.take(logs)
    np.testing.assert_array_equal(traces[0][:, 0], [0, 0, 2, 2, 4])  # a prediction every 2nd call, held
    np.testing.assert_array_equal(traces[1][:, 1], [100.5, 100.5])
    np.testing.assert_array_equal(traces[2][:, 0], [0, 0, 2])
    assert traces[3].shape == (1, 2)
    runner.reset()
    runner.act_batch([{}, {}])
    with pytest.raises(ValueError, match="3 episodes were logged but 2 were scored"):
        runner.take(logs[:3])
    runner.reset()
    runner.act_batch([{}, {}])
    with pytest.raises(ValueError, match="has 5 steps but 1 scored calls"):
        runner.take(logs[:2])


def test_the_calibrate_flags_are_the_policy_score_choices():
    from lerobot_policy_ensemble_diffusion.configuration_ensemble_diffusion import SCORE_CHOICES

    assert tuple(SCORE_CHOICES) == SCORE_CHOICE_FIELDS


def test_score_study_needs_enough_nominal_episodes_for_its_threshold(tiny_policy_dir):
    with pytest.raises(ValueError, match="at least 19 nominal episodes"):
        ScoreStudyConfig(policy=PolicyPathConfig(path=tiny_policy_dir), nominal_episodes=10)


def test_rescoring_with_the_policy_own_choice_gives_its_logged_score(tiny_policy_dir):
    runner = PolicyRunner.from_pretrained(tiny_policy_dir, GateMode.REPORT)
    assert len(choice_grid(runner.policy)) == 3 * 2 * 2  # one sample per member: one source
    runner.policy.config.uncertainty_samples_per_member = 2
    choices = choice_grid(runner.policy)
    assert choices[0] == {name: getattr(runner.policy.config, name) for name in SCORE_CHOICE_FIELDS}
    assert len({choice_label(c) for c in choices}) == len(choices) == 3 * 2 * 3 * 2
    rescoring = RescoringRunner(runner, choices)

    def make_env():
        kwargs = env_kwargs_for_policy(runner.policy.config)
        return gym.make(lerobot_suture.ENV_ID, disable_env_checker=True, max_episode_steps=9, **kwargs)

    logs = rollout_seeds(make_env, rescoring, [0, 1, 2], batch_envs=2)
    traces = rescoring.take(logs)
    assert [t.shape for t in traces] == [(9, len(choices))] * 3
    for log, trace in zip(logs, traces, strict=True):
        np.testing.assert_allclose(trace[:, 0], log.scores, rtol=1e-6)
        assert np.all(np.isfinite(trace)) and len(np.unique(trace[0])) > len(choices) // 2


def test_score_study_writes_table_figure_and_numbers(tiny_policy_dir, tmp_path):
    """The score study at toy scale (an untrained tiny ensemble, 2 nominal episodes, one run per scenario):
    every file it writes, and what is in each."""
    policy = tmp_path / "policy"
    shutil.copytree(tiny_policy_dir, policy)  # no calibration: the study needs none
    out = tmp_path / "study"
    cli_main(
        [
            "score-study",
            f"--policy.path={policy}",
            f"--output_dir={out}",
            "--nominal_episodes=2",
            "--runs_per_scenario=1",
            "--alpha=0.4",
        ]
    )
    result = json.loads((out / "score_study.json").read_text())
    assert len(result["choices"]) == 12  # the tiny policy draws one sample per member
    assert sum(row["policy_own"] for row in result["choices"]) == 1
    row = result["choices"][0]
    assert set(row["scenarios"]) == {
        "needle_drop",
        "camera_moved",
        "phantom_servo",
        "phantom_moved_after_insertion",
    }
    assert all(math.isfinite(r["threshold"]) for r in result["choices"])
    own = next(r for r in result["choices"] if r["policy_own"])
    assert own["label"] == "max_abs_cov/normalized/total/horizon" and own["threshold"] > 0
    # The table: one row per choice in the JSON's order, best rank score first, the policy's own in bold.
    table = (out / "score_study.md").read_text()
    rows = [line.split(" | ") for line in table.splitlines() if line.startswith("| ")][1:]
    assert [r[0].removeprefix("| ") for r in rows] == [
        f"**{c['label']}**" if c["policy_own"] else c["label"] for c in result["choices"]
    ]
    ranks = [math.nan if r[1] == "n/a" else float(r[1]) for r in rows]
    assert ranks == pytest.approx([c["rank_score"] for c in result["choices"]], abs=5.1e-4, nan_ok=True)
    finite = [x for x in ranks if not math.isnan(x)]
    assert finite == sorted(finite, reverse=True) and ranks[: len(finite)] == finite
    # The figure: not one flat colour, and its two AUROC heatmaps drawn in colour over a good part of it.
    image = np.asarray(Image.open(out / "score_study.png").convert("RGB"), dtype=float)
    assert image.mean(axis=2).std() > 5, "score_study.png is blank"
    coloured = image.max(axis=2) - image.min(axis=2) > 60
    assert coloured.mean() > 0.2, f"only {coloured.mean():.0%} of score_study.png is heatmap"
    assert {p.name for p in out.iterdir()} == {"score_study.json", "score_study.md", "score_study.png"}
