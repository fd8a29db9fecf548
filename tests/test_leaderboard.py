"""`lerobot-suture leaderboard`: cells, seeds, the board a user's checkpoint joins, and the whole pipeline."""

import json
import math
from pathlib import Path

import pytest
from PIL import Image

from lerobot_suture.cli import main as cli_main
from lerobot_suture.leaderboard.board import BOARD_DPI, plot, render
from lerobot_suture.leaderboard.cells import (
    best_rows,
    condition_seeds,
    conditions,
    row_summary,
    seed_spread,
    seed_spreads,
    summarize_cell,
)
from lerobot_suture.leaderboard.pipeline import (
    PRESET_SEED,
    LeaderboardConfig,
    default_shifts,
    parse_checkpoints,
)
from lerobot_suture.leaderboard.run import rounded, seeded_rows
from lerobot_suture.runtime.config import PolicyPathConfig
from lerobot_suture.runtime.rollout import EpisodeLog, StepLog
from lerobot_suture.sim.shifts import SHIFTS
from lerobot_suture.sim.shifts import default_shifts as every_shift
from lerobot_suture.sim.tasks import TASK_NAMES


def _step(score=math.nan, ood=False, active=False, intervened=False):
    return StepLog(
        score=score,
        threshold=1.0,
        ood=ood,
        released=False,
        new_prediction=True,
        controller="policy",
        perturbed=False,
        needle_in_tissue=False,
        cbf_active=active,
        cbf_intervened=intervened,
    )


def test_cell_summary_counts_success_gate_and_cbf():
    ok = EpisodeLog(seed=1, scenario="nominal", success=True, steps=[_step(0.1), _step(0.2, active=True)])
    ok.h_min_physics = 0.3
    flagged = EpisodeLog(
        seed=2, scenario="nominal", steps=[_step(0.1, active=True, intervened=True), _step(2.0, ood=True)]
    )
    flagged.h_min_physics = -0.01
    cell = summarize_cell([ok, flagged], seconds=1.0)
    assert cell["episodes"] == 2 and cell["successes"] == 1 and cell["success_rate"] == 0.5
    low, high = cell["success_interval"]
    assert 0.0 < low < 0.5 < high < 1.0
    assert cell["gate"] == {"flagged": 1, "flagged_rate": 0.5, "flagged_failures": 1, "failures": 1}
    assert cell["cbf"]["active_steps"] == 2 and cell["cbf"]["intervention_rate"] == 0.5
    assert cell["cbf"]["violating_episodes"] == 1 and cell["cbf"]["h_min"] == -0.01
    assert cell["per_episode"] == [[1, True, 2, None], [2, False, 2, 1]]
    # A policy without a gate (NaN scores) has no gate figures, not zero alarms.
    assert summarize_cell([EpisodeLog(seed=3, scenario="nominal", steps=[_step()])], 1.0)["gate"] is None


def test_a_cells_episodes_are_packed_as_columns_on_the_board_and_unpack_to_the_same_rows():
    from lerobot_suture.leaderboard.cells import packed_episodes, unpacked_episodes

    rows = [[7000000, True, 60, None], [7000001, False, 58, 12], [7000002, True, 59, None]]
    packed = packed_episodes(rows)
    assert packed == {
        "first_seed": 7000000,
        "success": "101",
        "steps": [60, 58, 59],
        "first_alarm": {"1": 12},
    }
    assert unpacked_episodes(packed) == rows
    gapped = [[3, False, 2, 0], [9, True, 4, None]]  # seeds that do not run on are kept whole
    assert packed_episodes(gapped)["seeds"] == [3, 9] and unpacked_episodes(packed_episodes(gapped)) == gapped
    assert unpacked_episodes(packed_episodes([])) == []
    committed = json.loads(
        (Path(__file__).parents[1] / "docs/results/leaderboard/leaderboard.json").read_text()
    )
    cell = committed["tasks"]["insertion"]["ensemble_diffusion"]["nominal"]
    episodes = unpacked_episodes(cell["per_episode"])
    assert len(episodes) == cell["episodes"] and sum(e[1] for e in episodes) == cell["successes"]


def test_a_running_suture_cell_says_how_far_into_the_suture_its_episodes_got(tmp_path):
    def suture(seed, on_marks):
        # Every throw on the marks but the last was extracted: the episode went on to the next one.
        results = [
            {"throw": k, "entry_error_m": 0.001, "exit_error_m": 0.001, "on_marks": ok, "over_step": 10 * k}
            | {"extracted": ok and k < len(on_marks) - 1}
            for k, ok in enumerate(on_marks)
        ]
        return EpisodeLog(
            seed=seed,
            scenario="nominal",
            success=len(on_marks) == 4 and all(on_marks),
            steps=[_step()],
            throw_results=results,
        )

    logs = [suture(1, [True, True, False]), suture(2, [False]), suture(3, []), suture(4, [True] * 4)]
    cell = summarize_cell(logs, 1.0, throws=4)
    first, second, third, fourth = cell["per_throw"]["throws"]
    assert [t["on_marks"]["count"] for t in (first, second, third, fourth)] == [2, 2, 1, 1]
    assert first["off_marks"] == 1 and first["unfinished"] == 1 and third["reached"] == 2
    assert cell["successes"] == 1
    summary = row_summary({"nominal": cell}, ["nominal"])
    assert summary["nominal_throws_on_marks"] == pytest.approx((2 + 0 + 0 + 4) / 4)
    table = render(
        {"episodes": 4, "shifts": [], "tasks": {"running_suture": {"ensemble": {"nominal": cell}}}}
    )
    assert "throws on the marks a nominal episode, mean |" in table and "| 1.50 |" in table
    assert ", throws 1.50 |" in table
    # The figure gives the suture a second panel, the throws on the marks: two panels' height.
    # A row whose cells were summarized without the throws (an earlier board) is drawn beside it.
    older = {k: v for k, v in cell.items() if k != "per_throw"}
    board = {
        "episodes": 4,
        "shifts": [],
        "tasks": {"running_suture": {"older": {"nominal": older}, "ensemble": {"nominal": cell}}},
    }
    with Image.open(plot(board, tmp_path / "board.png")) as image:
        assert image.size == (12 * BOARD_DPI, int(2 * 3.2 * BOARD_DPI))
    # A task of one throw or none has no throw figures.
    assert "per_throw" not in summarize_cell(logs, 1.0)
    assert row_summary({"nominal": summarize_cell(logs, 1.0)})["nominal_throws_on_marks"] is None


def test_conditions_and_seeds_are_shared_by_policies_and_disjoint_across_cells():
    conds = conditions("insertion", ["dim_light@0.2", "action_delay@1"])
    assert conds[0] == "nominal" and conds[-2:] == ["shift:dim_light@0.2", "shift:action_delay@1"]
    seeds = {
        (task, c): condition_seeds(7_000_000, task, c, 50)
        for task in TASK_NAMES
        for c in conditions(task, [s.label for s in every_shift()])  # both magnitudes of each
    }
    # One seed set a scene: no seed serves two cells, except the magnitudes of one shift, which are paired.
    scenes = {(task, c.partition("@")[0]): group for (task, c), group in seeds.items()}
    flat = [s for group in scenes.values() for s in group]
    assert len(flat) == len(set(flat))
    assert seeds[("insertion", "shift:dim_light@0.2")] == seeds[("insertion", "shift:dim_light@0.6")]
    assert condition_seeds(7_000_000, "insertion", "nominal", 50) == seeds[("insertion", "nominal")]
    assert len(default_shifts()) == len(SHIFTS)


@pytest.mark.parametrize(
    ("args", "match"),
    [
        ({"tasks": ["knot_tying"]}, "tasks"),
        ({"policies": ["pi0"]}, "policies"),
        ({"episodes": 0}, "episodes"),
        ({"shifts": ["fog@0.2"]}, "Unknown shift"),
        ({"checkpoints": ["insertion=outputs/x"]}, "TASK:POLICY=DIR"),
        ({"policy": PolicyPathConfig(num_inference_steps=2)}, "apply to the checkpoint of `--policy.path`"),
        ({"train_seeds": [PRESET_SEED, 2000]}, "not the presets' own"),
        ({"train_seeds": [2000, 2000]}, "distinct"),
        ({"train_seeds": [2000], "seeded_rows": ["insertion:pi0"]}, "TASK:POLICY"),
        ({"train_seeds": [2000], "tasks": ["pickup"], "seeded_rows": ["insertion:act"]}, "TASK:POLICY"),
    ],
)
def test_bad_config_names_the_field(args, match):
    with pytest.raises(ValueError, match=match):
        LeaderboardConfig(**args)


def test_every_preset_trains_with_the_seed_the_board_s_rows_are_said_to_have():
    from lerobot_suture.leaderboard.pipeline import POLICY_PRESETS, TASK_RECIPES

    presets = [*POLICY_PRESETS.values(), *(preset for _, preset in TASK_RECIPES.values())]
    assert {json.loads(p.read_text())["seed"] for p in presets} == {PRESET_SEED}


def _cell(successes: int, n: int = 10) -> dict:
    logs = [EpisodeLog(seed=k, scenario="nominal", success=k < successes, steps=[_step()]) for k in range(n)]
    return summarize_cell(logs, 1.0)


def test_a_row_s_spread_over_training_seeds_and_the_rows_seeded_by_default():
    spread = seed_spread({1000: _cell(6), 2000: _cell(2), 3000: _cell(7)})
    assert spread["seeds"] == [1000, 2000, 3000]
    assert spread["success_mean"] == pytest.approx(0.5) and spread["success_range"] == [0.2, 0.7]
    low, high = spread["per_seed"]["2000"]["success_interval"]
    assert low < 0.2 < high
    board = {
        "tasks": {"insertion": {"act": {"nominal": _cell(6), "shift:dim_light@0.2": _cell(5)}}},
        "seeds": {"insertion": {"act": {"2000": {"nominal": _cell(2)}}}},
    }
    spreads = seed_spreads(board, PRESET_SEED)
    assert list(spreads["insertion"]["act"]) == ["nominal"]  # the further seeds run no shifts
    assert spreads["insertion"]["act"]["nominal"]["seeds"] == [PRESET_SEED, 2000]
    board["seed_spread"], board["episodes"] = spreads, 10
    assert "| act | nominal | 40 [20, 60] | 1000: 60 [" in render(board)
    summary = {
        "act": {"nominal_success": 0.2, "scenario_success_mean": 0.1},
        "diffusion": {"nominal_success": 0.2, "scenario_success_mean": 0.3},
        "ensemble_diffusion": {"nominal_success": 0.9, "scenario_success_mean": None},
    }
    assert best_rows(summary) == ["ensemble_diffusion", "diffusion"]
    cfg = LeaderboardConfig(tasks=["insertion", "pickup", "extraction"], train_seeds=[2000, 3000])
    rows = seeded_rows(cfg, {"summary": {"pickup": summary}})
    assert rows == [("insertion", p) for p in cfg.policies] + [
        ("pickup", "ensemble_diffusion"),
        ("pickup", "diffusion"),
    ]
    assert seeded_rows(LeaderboardConfig(), {"summary": {"pickup": summary}}) == []


def test_a_joining_checkpoint_names_its_task(tiny_policy_dir):
    with pytest.raises(ValueError, match="--tasks"):
        LeaderboardConfig(policy=PolicyPathConfig(path=tiny_policy_dir))
    assert LeaderboardConfig().tasks == list(TASK_NAMES)


def test_checkpoint_entries_need_a_trained_policy(tmp_path):
    with pytest.raises(FileNotFoundError, match="config.json"):
        parse_checkpoints([f"insertion:act={tmp_path}"])
    (tmp_path / "config.json").write_text("{}")
    assert parse_checkpoints([f"insertion:act={tmp_path}"]) == {("insertion", "act"): tmp_path}


@pytest.mark.slow
def test_a_users_checkpoint_joins_the_board_and_finished_cells_are_kept(tiny_policy_dir, tmp_path, capsys):
    results, work = tmp_path / "results", tmp_path / "work"
    args = [
        f"--policy.path={tiny_policy_dir}",
        "--tasks=[insertion]",
        "--episodes=1",
        "--batch_envs=1",
        "--shifts=[dim_light@0.2]",
        f"--output_dir={work}",
        f"--results_dir={results}",
    ]
    cli_main(["leaderboard", *args, "--policy_name=mine"])
    board = json.loads((results / "leaderboard.json").read_text())
    row = board["tasks"]["insertion"]["mine"]
    assert list(row) == conditions("insertion", ["dim_light@0.2"])
    assert all(cell["episodes"] == 1 for cell in row.values())
    assert row["nominal"]["gate"] is not None  # the ensemble reports its gate
    assert "| nominal |" in (results / "leaderboard.md").read_text()
    with Image.open(results / "leaderboard.png") as image:
        assert len(set(image.convert("L").getdata())) > 10  # not blank
    assert "leaderboard.md" in capsys.readouterr().out

    # Finished cells are read back, not run again; a second row joins beside the first.
    cell_files = sorted((work / "cells").rglob("*.json"))
    stamps = [f.stat().st_mtime_ns for f in cell_files]
    cli_main(["leaderboard", *args, "--policy_name=theirs"])
    assert [f.stat().st_mtime_ns for f in cell_files] == stamps
    board = json.loads((results / "leaderboard.json").read_text())
    assert set(board["tasks"]["insertion"]) == {"mine", "theirs"}
    assert {"evaluate insertion mine", "evaluate insertion theirs"} <= set(board["timings"])
    assert board["tasks"]["insertion"]["theirs"]["nominal"]["per_episode"] == row["nominal"]["per_episode"]
    assert "| mine | theirs |" in render(board)
    summary = board["summary"]["insertion"]["mine"]
    assert summary["nominal_success"] == row["nominal"]["success_rate"]
    assert (
        summary["episodes"] == len(row)
        and summary["shift_success_mean"] == row["shift:dim_light@0.2"]["success_rate"]
    )

    # An approximation is its own row by default, and a named row's cells run as trained are not reused
    # for it.
    theirs = sorted((work / "cells" / "insertion" / "theirs").glob("*.json"))
    theirs_stamps = [f.stat().st_mtime_ns for f in theirs]
    cli_main(["leaderboard", *args, "--policy.num_inference_steps=2"])
    cli_main(["leaderboard", *args, "--policy_name=mine", "--policy.num_inference_steps=2"])
    assert [f.stat().st_mtime_ns for f in theirs] == theirs_stamps
    board = json.loads((results / "leaderboard.json").read_text())
    approximated = board["tasks"]["insertion"]["ensemble_diffusion S=2"]
    assert approximated["nominal"]["policy_overrides"] == {"num_inference_steps": 2}
    assert board["tasks"]["insertion"]["mine"]["nominal"]["policy_overrides"] == {"num_inference_steps": 2}

    # A joining row with a shift the others lack: a line of the table, "-" for the others; the summary
    # stays over the board's conditions. A row lacking one of those has no mean over the shifts.
    wider = [a for a in args if not a.startswith("--shifts")] + ["--shifts=[dim_light@0.2,dim_light@0.6]"]
    cli_main(["leaderboard", *wider, "--policy_name=mine", "--policy.num_inference_steps=2"])
    board = json.loads((results / "leaderboard.json").read_text())
    assert board["shifts"] == ["dim_light@0.2"]
    mine = board["tasks"]["insertion"]["mine"]
    assert (
        board["summary"]["insertion"]["mine"]["shift_success_mean"]
        == mine["shift:dim_light@0.2"]["success_rate"]
    )
    line = next(x for x in render(board).splitlines() if x.startswith("| shift:dim_light@0.6 |"))
    assert line.count(" - ") == len(board["tasks"]["insertion"]) - 1
    del board["tasks"]["insertion"]["theirs"]["shift:dim_light@0.2"]
    assert (
        row_summary(board["tasks"]["insertion"]["theirs"], conditions("insertion", board["shifts"]))[
            "shift_success_mean"
        ]
        is None
    )

    # The robustness report reads the board's shift cells, each with its interval and the gate's flags.
    report_dir = tmp_path / "robustness"
    board_file = results / "leaderboard.json"
    cli_main(["robustness-report", f"--leaderboard={board_file}", "--rows=[a=mine,b=theirs]",
              f"--output_dir={report_dir}"])  # fmt: skip
    report = json.loads((report_dir / "robustness.json").read_text())
    assert [r["shift"] for r in report["policies"]["a"]["shifts"]] == ["dim_light@0.2", "dim_light@0.6"]
    assert [r["shift"] for r in report["policies"]["b"]["shifts"]] == ["dim_light@0.2"]
    assert report["policies"]["a"]["shifts"][0]["runs"] == 1
    assert "| dim_light@0.2 | appearance | untrained |" in (report_dir / "robustness.md").read_text()
    with pytest.raises(SystemExit):
        cli_main(["robustness-report", f"--leaderboard={board_file}", "--rows=[a=nobody]"])
    assert "no row ['nobody']" in capsys.readouterr().err

    # A row run on another number of episodes (or seeds) would not compare: refused, the board kept.
    capsys.readouterr()
    with pytest.raises(SystemExit):
        cli_main(["leaderboard", *args, "--policy_name=other", "--episodes=2"])
    assert "Pass --episodes=1 to join it" in capsys.readouterr().err
    assert "other" not in json.loads((results / "leaderboard.json").read_text())["tasks"]["insertion"]


def test_an_approximation_must_leave_at_least_one_step_and_sample():
    with pytest.raises(ValueError, match="policy.uncertainty_samples_per_member"):
        PolicyPathConfig(uncertainty_samples_per_member=0)
    assert PolicyPathConfig(num_inference_steps=3).overrides == {"num_inference_steps": 3}
    assert PolicyPathConfig().overrides == {}


@pytest.mark.slow
def test_toy_leaderboard_trains_the_four_policies_and_ranks_them(tmp_path):
    """The whole pipeline at toy scale: record, train LeRobot's ACT and diffusion, the ensemble and its member
    with the real lerobot-train, calibrate, evaluate."""
    results = tmp_path / "results"
    cli_main(
        [
            "leaderboard",
            "--tasks=[insertion]",
            "--toy=true",
            "--episodes=1",
            "--shifts=[]",
            "--train_seeds=[1001]",
            "--seeded_rows=[insertion:ensemble_member]",
            f"--output_dir={tmp_path / 'work'}",
            f"--results_dir={results}",
        ]
    )
    board = json.loads((results / "leaderboard.json").read_text())
    assert set(board["tasks"]["insertion"]) == {"act", "diffusion", "ensemble_member", "ensemble_diffusion"}
    # The member trained again from a further seed: calibrated, on nominal and the scenarios.
    seeded = board["seeds"]["insertion"]["ensemble_member"]["1001"]
    assert list(seeded) == conditions("insertion", []) and seeded["nominal"]["gate"] is not None
    train_config = (
        tmp_path / "work/train/insertion/ensemble_member_seed1001/checkpoints/last/pretrained_model"
    )
    assert json.loads((train_config / "train_config.json").read_text())["seed"] == 1001
    assert board["seed_spread"]["insertion"]["ensemble_member"]["nominal"]["seeds"] == [1000, 1001]
    assert "calibrate insertion ensemble_member seed 1001" in board["timings"]
    assert "## insertion: training seeds" in (results / "leaderboard.md").read_text()
    assert board["tasks"]["insertion"]["act"]["nominal"]["gate"] is None
    # The ensemble's member as a single policy: one member of the ensemble's recipe, with its own gate.
    member = json.loads(
        (
            tmp_path / "work/train/insertion/ensemble_member/checkpoints/last/pretrained_model/config.json"
        ).read_text()
    )
    assert member["n_members"] == 1 and member["uncertainty_samples_per_member"] > 1
    assert board["tasks"]["insertion"]["ensemble_member"]["nominal"]["gate"] is not None
    assert "calibrate insertion ensemble_member" in board["timings"]
    assert {"record insertion", "train insertion act", "evaluate insertion diffusion"} <= set(
        board["timings"]
    )


@pytest.mark.slow
def test_a_default_lerobot_train_act_checkpoint_evaluates_and_joins_the_board(tmp_path):
    """A new user's path: LeRobot's ACT trained by `lerobot-train --policy.type=act` with LeRobot's defaults on
    a recorded dataset lists the privileged needle target among its inputs (LeRobot makes every observation.*
    key one). It still runs under `lerobot-eval` and joins the board, with a warning that names the fix."""
    from robot_commands import run_command

    from lerobot_suture.datasets.features import NEEDLE_KEYPOINTS_KEY
    from lerobot_suture.datasets.record import record
    from lerobot_suture.datasets.record_config import RecordConfig

    data = tmp_path / "data"
    record(RecordConfig(repo_id="local/suture_act", root=str(data), num_episodes=2, val_fraction=0.5))
    train = tmp_path / "train"
    run_command(
        "lerobot-train",
        [
            "--policy.type=act",
            "--policy.pretrained_backbone_weights=null",
            "--policy.dim_model=32",
            "--policy.dim_feedforward=64",
            "--policy.n_encoder_layers=1",
            "--policy.n_vae_encoder_layers=1",
            "--policy.chunk_size=8",
            "--policy.n_action_steps=4",
            "--policy.device=cpu",
            "--policy.push_to_hub=false",
            "--dataset.repo_id=local/suture_act",
            f"--dataset.root={data}",
            "--steps=2",
            "--batch_size=2",
            "--num_workers=0",
            "--save_freq=2",
            f"--output_dir={train}",
        ],
        timeout=600,
    )
    checkpoint = train / "checkpoints" / "last" / "pretrained_model"
    assert NEEDLE_KEYPOINTS_KEY in json.loads((checkpoint / "config.json").read_text())["input_features"]
    run_command(
        "lerobot-eval",
        [
            f"--policy.path={checkpoint}",
            "--env.type=suture",
            "--eval.n_episodes=1",
            "--eval.batch_size=1",
            "--policy.device=cpu",
            f"--output_dir={tmp_path / 'eval'}",
        ],
        timeout=600,
    )
    results = tmp_path / "results"
    cli_main(
        [
            "leaderboard",
            f"--policy.path={checkpoint}",
            "--policy_name=users_act",
            "--tasks=[insertion]",
            "--episodes=1",
            "--batch_envs=1",
            "--shifts=[]",
            f"--output_dir={tmp_path / 'work'}",
            f"--results_dir={results}",
        ]
    )
    row = json.loads((results / "leaderboard.json").read_text())["tasks"]["insertion"]["users_act"]
    assert all(cell["episodes"] == 1 for cell in row.values())


def test_tuning_chooses_on_validation_seeds_apart_from_the_test_seeds(monkeypatch):
    from lerobot_suture.leaderboard import tuning
    from lerobot_suture.leaderboard.tuning import (
        check_validation_seeds_are_apart,
        choose,
        families,
        validation_base,
    )
    from lerobot_suture.runtime.seeds import SEED_STRIDE

    assert families(list(LeaderboardConfig().policies)) == ["act", "diffusion", "ensemble_diffusion"]
    scores = {
        "preset": {"mean": 0.5, "nominal": 0.9},
        "lerobot_defaults": {"mean": 0.6, "nominal": 0.7},
        "small": {"mean": 0.6, "nominal": 0.8},
    }
    assert choose(scores) == "small"
    assert (
        choose({"preset": {"mean": 0.5, "nominal": 0.5}, "other": {"mean": 0.5, "nominal": 0.5}}) == "preset"
    )
    cfg = LeaderboardConfig()
    check_validation_seeds_are_apart(cfg)  # the default bases: no validation seed is a test seed
    assert validation_base(cfg) != cfg.seed
    monkeypatch.setattr(tuning, "VALIDATION_OFFSET", SEED_STRIDE)  # the scenarios' groups, one further on
    with pytest.raises(ValueError, match="validation seeds are test seeds"):
        check_validation_seeds_are_apart(cfg)
    with pytest.raises(ValueError, match="`tune`"):
        LeaderboardConfig(tune=True, train_seeds=[2000])


@pytest.mark.slow
def test_toy_tuning_trains_each_configuration_and_writes_the_chosen_preset(tmp_path):
    from lerobot_suture.leaderboard.tuning import CONFIGURATIONS

    results = tmp_path / "results"
    cli_main(
        [
            "leaderboard",
            "--tune=true",
            "--policies=[act]",
            "--toy=true",
            "--episodes=1",
            f"--output_dir={tmp_path / 'work'}",
            f"--results_dir={results}",
        ]
    )
    report = json.loads((results / "tuning.json").read_text())
    act = report["families"]["act"]
    assert set(act["configurations"]) == set(CONFIGURATIONS["act"])
    assert list(act["configurations"]["preset"]["validation"]) == conditions("insertion", [])
    preset = json.loads((results / "presets" / "act.json").read_text())
    chosen_flags = act["configurations"][act["chosen"]]["flags"]
    for flag in chosen_flags:
        name, value = flag.removeprefix("--policy.").split("=")
        assert str(preset["policy"][name]) == str(float(value) if "e-" in value else int(value)), flag
    assert report["validation_seed"] == 7_000_000 + 500_000
    assert "| act | half_encoder |" in (results / "tuning.md").read_text()


def test_the_board_file_keeps_six_significant_digits_of_every_float_of_its_cells_and_the_rest_as_it_was():
    board = {
        "a": [0.07134759913335872, 6.938893903907228e-18, 3, True, None],
        "b": {"c": 1234567.891, "d": "x"},
    }
    assert rounded(board) == {"a": [0.0713476, 6.93889e-18, 3, True, None], "b": {"c": 1234570.0, "d": "x"}}
    committed = json.loads(
        (Path(__file__).parents[1] / "docs/results/leaderboard/leaderboard.json").read_text()
    )
    assert rounded(committed["tasks"]) == committed["tasks"]  # written by the board as it writes now
