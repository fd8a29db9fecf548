"""`lerobot-suture dagger`: its flags, the three arms' new frames, their merge with the demonstrations, and a
toy loop end to end (resumed without redoing a stage)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from lerobot_suture.dagger import aggregate as agg
from lerobot_suture.dagger import collect as col
from lerobot_suture.dagger.config import ARMS, DaggerConfig
from lerobot_suture.surgeon.record_run import ACTOR_KEY, IS_INTERVENTION_KEY, UNCERTAINTY_KEY

HANDOVER_SEED = 5_000_004
"""A seed on which the tiny policy's gate (threshold :data:`THRESHOLD`) releases control mid-episode."""
THRESHOLD = 1.995


@pytest.fixture(scope="module")
def demo_root(tmp_path_factory) -> Path:
    """Three expert demonstrations at 96 px (the tiny policy's size): two train, one validation."""
    from lerobot_suture.datasets.record import record
    from lerobot_suture.datasets.record_config import RecordConfig

    root = tmp_path_factory.mktemp("dagger_demo") / "demo"
    record(
        RecordConfig(repo_id="suture-tests/dagger_demo", root=str(root), num_episodes=3, val_fraction=0.25)
    )
    return root


@pytest.fixture(scope="module")
def gated_policy(tiny_policy_dir, tmp_path_factory) -> Path:
    """The tiny policy with a gate whose threshold sits at :data:`THRESHOLD`."""
    from lerobot_suture.safety.ood.calibration import fit_calibration
    from lerobot_suture.safety.ood.calibration_file import save_calibration

    directory = tmp_path_factory.mktemp("dagger_policy") / "policy"
    shutil.copytree(tiny_policy_dir, directory)
    scores = THRESHOLD * (1 + 1e-4 * np.random.default_rng(0).standard_normal(100))
    save_calibration(fit_calibration(scores, model="normal"), directory, filename="ood_calibration.json")
    return directory


@pytest.fixture(scope="module")
def collected(gated_policy, demo_root, tmp_path_factory) -> dict:
    """The three arms' new frames on the same seeds, the ungated and bc arms on the gated arm's budget."""
    from lerobot_suture.datasets.metadata import read_episode_log
    from lerobot_suture.expert import ExpertConfig
    from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy

    runner = PolicyRunner.from_pretrained(gated_policy, GateMode.REPORT)
    log = read_episode_log(demo_root)
    spec = col.CollectSpec(
        env_kwargs_for_policy(runner.policy.config),
        {"nominal": [HANDOVER_SEED], "camera_moved": [HANDOVER_SEED + 1]},
        ExpertConfig(**log["expert"]["config"]),
    )
    gated, gated_runs = col.collect_gated(runner, spec)
    budget = col.frame_count(gated)
    ungated, ungated_runs = col.collect_ungated(runner, spec, budget, seed=1)
    bc, bc_runs = col.collect_bc(spec, budget)
    out = tmp_path_factory.mktemp("dagger_new")
    roots = {
        arm: col.write_episodes(episodes, out / arm, f"suture-tests/dagger_{arm}", spec)
        for arm, episodes in (("gated", gated), ("ungated", ungated), ("bc", bc))
    }
    return {
        "episodes": {"gated": gated, "ungated": ungated, "bc": bc},
        "runs": {"gated": gated_runs, "ungated": ungated_runs, "bc": bc_runs},
        "roots": roots,
        "budget": budget,
    }


# ------------------------------------------------------------------ flags


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        ({}, ValueError, "`--policy.path` is required"),
        ({"policy": "P"}, ValueError, "`--dataset_root` is required"),
        ({"policy": "P", "dataset_root": "D", "rounds": 0}, ValueError, "`rounds` must be >= 1"),
        ({"policy": "P", "dataset_root": "D", "arms": "gated,dagger"}, ValueError, "distinct arms from"),
        ({"policy": "P", "dataset_root": "D", "arms": "gated,gated"}, ValueError, "distinct arms from"),
        ({"policy": "P", "dataset_root": "D", "arms": "ungated,bc"}, ValueError, "set `--frames_per_round`"),
        (
            {"policy": "P", "dataset_root": "D", "calibration_episodes": 10},
            ValueError,
            "at least 19 calibration",
        ),
        ({"policy": "P", "dataset_root": "D", "lr": 0.0}, ValueError, "`lr` must be a finite number > 0"),
        ({"policy": "P", "dataset_root": "D", "alpha": 0.5}, ValueError, "`alpha` must be in"),
        (
            {"policy": "P", "dataset_root": "D", "collect_episodes": 0},
            ValueError,
            "`collect_episodes` must be >= 1",
        ),
        (
            {"policy": "P", "dataset_root": "D", "new_data_repeats": 0},
            ValueError,
            "`new_data_repeats` must be >= 1",
        ),
        ({"patience": 0}, ValueError, r"`watch.patience` must be >= 1 \(steps\)"),
        ({"position": float("nan")}, ValueError, r"`watch.position` must be a distance > 0 \(m\)"),
        ({"angle": -0.1}, ValueError, r"`watch.angle` must be an angle > 0 \(rad\)"),
        (
            {"policy": "/nonexistent/pretrained_model", "dataset_root": "D"},
            FileNotFoundError,
            "No trained policy",
        ),
    ],
)
def test_bad_settings_name_the_fix(kwargs, error, match):
    from lerobot_suture.dagger.watch import WatchConfig
    from lerobot_suture.runtime.config import PolicyPathConfig

    if {"patience", "position", "angle"} & set(kwargs):
        with pytest.raises(error, match=match):
            WatchConfig(**kwargs)
        return
    policy = kwargs.pop("policy", None)
    with pytest.raises(error, match=match):
        DaggerConfig(policy=PolicyPathConfig(path=policy and Path(policy)), **kwargs)


def test_dataset_without_episode_log_or_validation_is_refused(tiny_policy_dir, demo_root, tmp_path):
    from lerobot_suture.runtime.config import PolicyPathConfig

    policy = PolicyPathConfig(path=tiny_policy_dir)
    with pytest.raises(FileNotFoundError, match="not a dataset recorded by `lerobot-suture record`"):
        DaggerConfig(policy=policy, dataset_root=tmp_path)
    no_val = tmp_path / "no_val"
    shutil.copytree(demo_root / "meta", no_val / "meta")
    log_path = no_val / "meta" / "suture_episodes.json"
    log = json.loads(log_path.read_text())
    log["splits"]["val"] = []
    log_path.write_text(json.dumps(log))
    with pytest.raises(ValueError, match="record it with `--val_fraction` > 0"):
        DaggerConfig(policy=policy, dataset_root=no_val)
    log["splits"]["val"] = [0]
    log["env_kwargs"]["relative_actions"] = True
    log_path.write_text(json.dumps(log))
    with pytest.raises(ValueError, match="holds relative actions"):
        DaggerConfig(policy=policy, dataset_root=no_val)
    cfg = DaggerConfig(policy=policy, dataset_root=demo_root, arms="bc,gated", toy=True)
    assert (
        cfg.arm_list == ["gated", "bc"]
        and cfg.finetune_steps == 2
        and cfg.calibration_mode == "per_prediction"
    )


def test_the_command_line_reports_a_bad_flag_in_one_line(capsys):
    from lerobot_suture.cli import main as cli_main

    with pytest.raises(SystemExit) as exit_:
        cli_main(["dagger", "--policy.path=P", "--dataset_root=D", "--arms=gated,nobody"])
    assert exit_.value.code == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert err[-1].startswith("lerobot-suture dagger: error: `arms` must be a comma-separated list")


# ------------------------------------------------------------------ selection


def test_spread_budget_is_even_and_capped_by_the_episodes():
    assert col.spread_budget([10, 10, 10], 9) == [3, 3, 3]
    assert col.spread_budget([2, 10, 10], 12) == [2, 5, 5]
    assert col.spread_budget([3, 4], 100) == [3, 4]
    assert col.spread_budget([5, 5, 5], 7) == [3, 2, 2]
    assert col.spread_budget([], 5) == [] and col.spread_budget([4], 0) == [0]


def test_surgeon_segments_and_truncation():
    frames = [{ACTOR_KEY: np.array([a]), "k": k} for k, a in enumerate([0, 1, 1, 0, 2, 1])]
    assert [[f["k"] for f in s] for s in col.surgeon_segments(frames)] == [[1, 2], [5]]
    episodes = [[1, 2, 3], [4, 5, 6], [7]]
    assert col.truncate(episodes, 5) == [[1, 2, 3], [4, 5]] and col.truncate(episodes, 0) == []


# ------------------------------------------------------------------ the arms


def test_gated_arm_keeps_only_the_surgeons_frames(collected):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_suture.datasets.video import resolve_video_backend

    episodes, runs = collected["episodes"]["gated"], collected["runs"]["gated"]
    frames = [f for e in episodes for f in e]
    assert frames and all(
        int(f[ACTOR_KEY][0]) == 1 and float(f[IS_INTERVENTION_KEY][0]) == 1.0 for f in frames
    )
    assert len(frames) == sum(r["surgeon_steps"] for r in runs)
    # The policy drove before the gate released control on this seed: its frames were left out.
    first = runs[0]
    assert first["seed"] == HANDOVER_SEED and first["handover_step"] > 0
    assert len(episodes[0]) == first["steps"] - first["handover_step"]

    run = LeRobotDataset(
        "suture-tests/dagger_gated", root=collected["roots"]["gated"], video_backend=resolve_video_backend()
    )
    assert run.meta.total_frames == len(frames)
    assert all(
        int(run[i][ACTOR_KEY]) == 1 and float(run[i][IS_INTERVENTION_KEY]) == 1.0 for i in range(len(run))
    )


def test_every_arm_gets_as_many_new_frames(collected):
    counts = {arm: col.frame_count(collected["episodes"][arm]) for arm in ARMS}
    assert counts["gated"] == collected["budget"] > 0
    assert counts == dict.fromkeys(ARMS, collected["budget"]), counts
    ungated = [f for e in collected["episodes"]["ungated"] for f in e]
    assert all(int(f[ACTOR_KEY][0]) == 0 and float(f[IS_INTERVENTION_KEY][0]) == 0.0 for f in ungated)
    assert len(collected["episodes"]["ungated"]) == 2  # a window of each episode
    bc = [f for e in collected["episodes"]["bc"] for f in e]
    assert all(int(f[ACTOR_KEY][0]) == 1 and float(f[IS_INTERVENTION_KEY][0]) == 0.0 for f in bc)


def test_ungated_labels_follow_the_state_the_policy_reached():
    """Watching the expert drive a whole episode, the labeller gives the expert's actions through approach,
    descent and drive; and it labels a needle already in tissue as the expert would drive it on."""
    import gymnasium as gym

    import lerobot_suture
    from lerobot_suture.expert import ExpertConfig, ScriptedExpert

    env = gym.make(lerobot_suture.ENV_ID, disable_env_checker=True, obs_type="state")
    recorder = col.LabellingRecorder(ExpertConfig())
    driver = ScriptedExpert()
    observation, _ = env.reset(seed=7)
    driver.reset(env)
    executed, phases, in_tissue_labels = [], [], []
    done = False
    while not done:
        recorder.observe(env)
        phases.append(driver.phase or "approach")
        action = driver.act(env)
        executed.append(action)
        if env.unwrapped.needle_in_tissue:  # a labeller that first sees the needle here
            late = col.StateLabeller(ExpertConfig())
            late.reset(env)
            in_tissue_labels.append((late.label(env), action))
        next_observation, reward, terminated, truncated, info = env.step(action)
        done = terminated or truncated
        recorder.add(env, observation, np.zeros(10, np.float32), reward, info, done, 0, 0.5, 0)
        observation = next_observation
    recorder.save_episode()
    env.close()
    assert info["is_success"] and {"approach", "descend", "drive"} <= set(phases)
    labels = np.array([f["action"] for f in recorder.dataset.episodes[0]])
    # In tissue the drive angle is read from the needle's measured rotation, a fraction of a mrad behind the
    # angle the driver commanded (metres and rotation-matrix entries: 5e-4 is far inside the expert's
    # 0.5 mm and 0.03 rad tolerances).
    np.testing.assert_allclose(labels, np.array(executed), atol=5e-4)
    assert in_tissue_labels
    for label, action in in_tissue_labels:
        np.testing.assert_allclose(label, action, atol=5e-4)


def test_pose_divergence_measures_the_jaw_targets_apart():
    from lerobot_suture.dagger.watch import pose_divergence
    from lerobot_suture.sim.geometry import rot6_from_matrix, rotation_about_z

    a = np.concatenate([[0.01, 0.02, 0.03], rot6_from_matrix(np.eye(3)), [1.0]])
    b = a.copy()
    b[:3] += [0.003, 0.0, -0.004]
    b[3:9] = rot6_from_matrix(rotation_about_z(0.2))
    b[9] = 0.0  # the jaw's closure is not judged
    assert pose_divergence(a, a) == pytest.approx((0.0, 0.0), abs=1e-9)
    assert pose_divergence(a, b) == pytest.approx((0.005, 0.2), abs=1e-9)


def test_watching_surgeon_spares_the_expert_and_takes_over_after_patience():
    """Commands that are the expert's own never stray; commands 5 mm off stray at every step, and the
    stand-in takes over at the patience-th of them, from a fresh count every episode."""
    import gymnasium as gym

    import lerobot_suture
    from lerobot_suture.dagger.watch import WatchConfig, WatchingExpertSurgeon
    from lerobot_suture.expert import ExpertConfig, ScriptedExpert

    env = gym.make(lerobot_suture.ENV_ID, disable_env_checker=True, obs_type="state")
    surgeon = WatchingExpertSurgeon(ExpertConfig(), WatchConfig(enabled=True, patience=3))
    driver = ScriptedExpert()
    env.reset(seed=7)
    driver.reset(env)
    surgeon.begin_episode(env)
    done = False
    while not done:
        action = driver.act(env)
        assert not surgeon.intervenes(env, action)
        *_, terminated, truncated, info = env.step(action)
        done = terminated or truncated
    assert info["is_success"]

    for _episode in range(2):
        env.reset(seed=8)
        driver.reset(env)
        surgeon.begin_episode(env)
        decisions = []
        for _step in range(4):
            action = driver.act(env)
            strayed = action.copy()
            strayed[2] += 0.005
            decisions.append(surgeon.intervenes(env, strayed))
            env.step(action)
        assert decisions == [False, False, True, True]
    env.close()


def test_gated_arm_with_a_watching_surgeon_records_its_takeover(gated_policy):
    """The tiny policy's commands stray from the expert's from the start: the watching stand-in takes
    over at the first step its patience allows, before the gate releases control, and its frames are kept."""
    from lerobot_suture.dagger.watch import WatchConfig
    from lerobot_suture.expert import ExpertConfig
    from lerobot_suture.runtime.policy import GateMode, PolicyRunner, env_kwargs_for_policy

    runner = PolicyRunner.from_pretrained(gated_policy, GateMode.REPORT)
    spec = col.CollectSpec(
        env_kwargs_for_policy(runner.policy.config),
        {"nominal": [HANDOVER_SEED]},
        ExpertConfig(),
        watch=WatchConfig(enabled=True, patience=2),
    )
    episodes, runs = col.collect_gated(runner, spec)
    (run,) = runs
    assert run["handover_reason"] == "taken over" and run["handover_step"] == 1
    assert len(episodes) == 1 and len(episodes[0]) == run["steps"] - 1 == run["surgeon_steps"]


def test_report_counts_who_started_each_collection_handover():
    from lerobot_suture.dagger.report import handover_reasons, markdown

    runs = [
        {"handover_step": 4, "handover_reason": "gate released"},
        {"handover_step": 2, "handover_reason": "taken over"},
        {"handover_step": 7, "handover_reason": "taken over"},
        {"handover_step": None, "handover_reason": None},
        {"handover_step": 3},  # a run from before the reason was kept
    ]
    assert handover_reasons(runs) == {"gate released": 2, "taken over": 2}
    scenarios = ("nominal", "phantom_moved_after_insertion", "camera_moved", "phantom_servo")

    def row(round_, handovers):
        return {
            "arm": "gated",
            "round": round_,
            "new_frames": 10 * round_,
            "cumulative_frames": 10 * round_,
            "autonomous_success": dict.fromkeys(scenarios, 0.5),
            "success": dict.fromkeys(scenarios, 0.9),
            "overall_autonomous_success": 0.5,
            "overall_success": 0.9,
            "handovers_per_episode": 0.4,
            "surgeon_steps_per_episode": 3.0,
            "nominal_false_alarms_per_episode": 0.0,
            "auroc": dict.fromkeys(scenarios[1:], 0.8),
            "test_episodes_per_scenario": 10,
            "collection_handovers": handovers,
        }

    plain = markdown([row(0, {}), row(1, {"gate released": 3})])
    assert "by who started it" not in plain
    watched = markdown([row(0, {}), row(1, {"gate released": 3, "taken over": 5})])
    assert "| round | the gate | the surgeon |" in watched and "| 1 | 3 | 5 |" in watched


def test_merged_dataset_holds_the_training_demonstrations_and_the_new_frames(
    collected, demo_root, gated_policy, tmp_path
):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_suture.datasets.split import train_episodes
    from lerobot_suture.datasets.video import resolve_video_backend

    demos = agg.training_demonstrations(demo_root, "suture-tests/dagger_demo", tmp_path / "demonstrations")
    demo_full = LeRobotDataset(
        "suture-tests/dagger_demo", root=demo_root, video_backend=resolve_video_backend()
    )
    train = train_episodes(demo_root)
    train_frames = sum(int(demo_full.meta.episodes[i]["length"]) for i in train)
    stats = agg.policy_normalizer_stats(gated_policy)
    roots = list(collected["roots"].values())
    out = agg.aggregate(demos, roots, tmp_path / "merged", "suture-tests/dagger_merged", stats)

    merged = LeRobotDataset("suture-tests/dagger_merged", root=out, video_backend=resolve_video_backend())
    new_frames = sum(col.frame_count(e) for e in collected["episodes"].values())
    new_episodes = sum(len(e) for e in collected["episodes"].values())
    assert merged.meta.total_episodes == len(train) + new_episodes
    assert merged.meta.total_frames == train_frames + new_frames
    first, last = merged[0], merged[len(merged) - 1]
    assert int(first[ACTOR_KEY]) == 1 and float(first[IS_INTERVENTION_KEY]) == 0.0  # a demonstration
    assert first["observation.images.endoscope"].shape == last["observation.images.endoscope"].shape
    # "Not consulted" stays NaN through LeRobot's merge, and a batch of frames collates (as lerobot-train's).
    assert torch.isnan(first[UNCERTAINTY_KEY]).all()
    batch = torch.utils.data.default_collate([merged[i] for i in range(len(merged))])
    assert batch[ACTOR_KEY].shape == (len(merged),)
    # The policy's normalization is kept, whatever the new frames' spread.
    for key, feature_stats in stats.items():
        for name, value in feature_stats.items():
            np.testing.assert_allclose(merged.meta.stats[key][name], value, rtol=1e-6)

    # Repeated, the new episodes weigh more in a uniformly sampled batch; the demonstrations appear once.
    out = agg.aggregate(demos, roots, tmp_path / "merged_x3", "suture-tests/dagger_x3", stats, repeats=3)
    tripled = LeRobotDataset("suture-tests/dagger_x3", root=out, video_backend=resolve_video_backend())
    assert tripled.meta.total_episodes == len(train) + 3 * new_episodes
    assert tripled.meta.total_frames == train_frames + 3 * new_frames
    np.testing.assert_array_equal(tripled[len(tripled) - 1]["action"], last["action"])


# ------------------------------------------------------------------ the loop


def test_report_pairs_each_rounds_autonomy_with_round_zero_by_seed(tmp_path):
    from lerobot_suture.dagger.config import SCENARIOS
    from lerobot_suture.dagger.report import write_report

    def evaluation(outcomes: dict[str, list[bool]], seeds_reversed: bool = False) -> dict:
        episodes = {}
        for scenario, autonomous in outcomes.items():
            listed = [
                {"seed": 100 + k, "autonomous_success": ok, "success": True}
                for k, ok in enumerate(autonomous)
            ]
            episodes[scenario] = listed[::-1] if seeds_reversed else listed
        rate = {s: float(np.mean(v)) for s, v in outcomes.items()}
        return {
            "scenarios": {
                s: {"autonomous_success": rate[s], "success": 1.0, "episodes": 10} for s in outcomes
            },
            "overall": {
                "autonomous_success": float(np.mean(list(rate.values()))),
                "success": 1.0,
                "handovers_per_episode": 0.1,
                "surgeon_steps_per_episode": 1.0,
            },
            "nominal_false_alarms_per_episode": 0.0,
            "auroc": dict.fromkeys(SCENARIOS[1:], 0.9),
            "episodes": episodes,
        }

    before = dict.fromkeys(SCENARIOS, [True] * 2 + [False] * 8)
    # Camera moved: four episodes turn autonomous, one stops being; the rest as before.
    after = {**before, "camera_moved": [False, True] + [True] * 4 + [False] * 4}
    for folder, result in (("round_0", evaluation(before)), ("gated/round_1", evaluation(after, True))):
        (tmp_path / folder).mkdir(parents=True)
        (tmp_path / folder / "eval.json").write_text(json.dumps(result))
    (tmp_path / "gated" / "round_1" / "collect.json").write_text(json.dumps({"new_frames": 40, "runs": []}))

    text = write_report(tmp_path, ["gated"], rounds=1)
    first, row = json.loads((tmp_path / "dagger.json").read_text())["rows"]
    assert "autonomous_change" not in first and first["autonomous_interval"]["nominal"][0] < 0.2
    change = row["autonomous_change"]["camera_moved"]
    # Paired by seed although round 1 lists its episodes in another order.
    assert (change["improved"], change["worsened"]) == (4, 1)
    assert change["change"] == pytest.approx(0.3) and change["p_value"] == pytest.approx(0.375)
    assert (
        row["autonomous_change"]["nominal"]["improved"] == 0
        and row["autonomous_change"]["nominal"]["change"] == 0
    )
    assert row["autonomous_interval"]["camera_moved"][0] < 0.5 < row["autonomous_interval"]["camera_moved"][1]
    assert "McNemar" in text and "+0.30 [" in text and ", 4 / 1, p = 0.38" in text


@pytest.mark.slow
def test_toy_loop_writes_the_table_and_resumes_without_redoing_a_stage(tiny_policy_dir, demo_root, tmp_path):
    from PIL import Image

    from lerobot_suture.dagger.loop import run_dagger
    from lerobot_suture.runtime.config import PolicyPathConfig

    def cfg():
        return DaggerConfig(
            policy=PolicyPathConfig(path=tiny_policy_dir),
            dataset_root=demo_root,
            rounds=1,
            output_dir=tmp_path / "dagger",
            toy=True,
            alpha=0.45,  # the untrained policy's gate then releases control in some episodes
        )

    first = run_dagger(cfg())
    out = tmp_path / "dagger"
    assert not first["skipped"] and len(first["ran"]) == 4 + 3 * 5
    rows = json.loads((out / "dagger.json").read_text())["rows"]
    assert [(r["arm"], r["round"]) for r in rows] == [(a, k) for a in ARMS for k in (0, 1)]
    new = {r["arm"]: r["new_frames"] for r in rows if r["round"] == 1}
    gated_frames = json.loads((out / "gated" / "round_1" / "collect.json").read_text())["new_frames"]
    assert new == dict.fromkeys(ARMS, gated_frames) and gated_frames > 0
    for row in rows:
        assert set(row["auroc"]) == {"phantom_moved_after_insertion", "camera_moved", "phantom_servo"}
        assert 0.0 <= row["overall_autonomous_success"] <= row["overall_success"] <= 1.0
    assert "| gated | 1 |" in (out / "dagger.md").read_text()
    image = np.asarray(Image.open(out / "dagger.png").convert("L"))
    assert image.shape[0] > 100 and image.std() > 5  # drawn, not blank
    for arm in ARMS:
        assert (out / arm / "round_1" / "train" / "checkpoints" / "last" / "pretrained_model").is_dir()

    evaluated = (out / "bc" / "round_1" / "eval.json").stat().st_mtime_ns
    again = run_dagger(cfg())
    assert again["ran"] == [] and len(again["skipped"]) == len(first["ran"])
    assert (out / "bc" / "round_1" / "eval.json").stat().st_mtime_ns == evaluated
    stages = json.loads((out / "stages.json").read_text())
    assert len(stages["invocations"]) == 2 and stages["invocations"][1]["ran"] == []
