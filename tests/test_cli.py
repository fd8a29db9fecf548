"""`lerobot-suture` given bad input: one line on stderr naming the problem and the fix, exit status 2."""

from __future__ import annotations

import sys

import pytest

from lerobot_suture.cli import SUBCOMMANDS
from lerobot_suture.cli import main as cli_main

NOWHERE = "/nonexistent/pretrained_model"


def _bad_input(argv: list[str], capsys) -> str:
    """Runs the command, expecting exit status 2 and one line on stderr; returns that line."""
    with pytest.raises(SystemExit) as exit_:
        cli_main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("INFO ")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.mark.parametrize(
    "argv, message",
    [
        ([], "lerobot-suture: error: a subcommand is required before any flag: one of demo, record"),
        (["--policy.path=x"], "lerobot-suture: error: a subcommand is required before any flag: one of demo"),
        (["bogus"], "lerobot-suture: error: unknown subcommand 'bogus': choose one of demo, record"),
    ],
)
def test_a_missing_or_unknown_subcommand_lists_the_subcommands(argv, message, capsys):
    line = _bad_input(argv, capsys)
    assert line.startswith(message) and "`lerobot-suture --help` says what each does" in line
    assert all(name in line for name in SUBCOMMANDS)


@pytest.mark.parametrize(
    "argv, message",
    [
        # Flags that do not parse, or that the config refuses.
        (["experiments", "--nonexistent=1"], "unrecognized arguments: --nonexistent=1"),
        (
            ["experiments", f"--policy.path={NOWHERE}", "--nominal_episodes=0"],
            "`nominal_episodes` must be >= 1",
        ),
        (["experiments", "--nominal_episodes"], "argument --nominal_episodes: expected one argument"),
        (["experiments"], "`--policy.path` is required"),
        (["cbf-replay", "--seed=abc"], "`seed`: Couldn't parse 'abc' into an int"),
        (["cbf-replay", "--bogus=1"], "unrecognized arguments: --bogus=1"),
        (["assemble", "--members=[a]", "--overwrite=maybe"], "`overwrite`"),
        (["assemble"], "`--output_dir` is required"),
        (["score-study", f"--policy.path={NOWHERE}", "--nominal_episodes=2"], "at least 19 nominal episodes"),
        (["score-study", "--alpha"], "argument --alpha: expected one argument"),
        (["demo", "--train_steps=abc"], "`train_steps`: Couldn't parse 'abc' into an int"),
        (["demo", "--scenarios=[earthquake]"], "`scenarios` must be drawn from"),
        (["demo", "--dataset_episodes=1"], "`dataset_episodes` must be 0 (no dataset) or >= 2"),
        (["demo", "--checkpoint_every=0"], "`train_steps` and `checkpoint_every` must be >= 1"),
        (["demo", "--frame_size=8"], "`frame_size` must be in [16, 640] px"),
        (
            ["calibrate", "--calibration_episodes=0", f"--policy.path={NOWHERE}"],
            "`calibration_episodes` must",
        ),
        (["record", "--bogus=1"], "unrecognized arguments: --bogus=1"),
        (["record", "--repo_id=a/b", "--num_episodes=1"], "`val_fraction`=0.25 holds out all 1 episode(s)"),
    ],
)
def test_a_bad_flag_is_named_in_one_line(argv, message, capsys):
    line = _bad_input(argv, capsys)
    assert line.startswith(f"lerobot-suture {argv[0]}: error: ") and message in line, line
    if argv[0] != "record" or "unrecognized" in message:
        assert f"`lerobot-suture {argv[0]} --help` lists the flags" in line


@pytest.mark.parametrize("command", ["experiments", "score-study", "calibrate"])
def test_a_policy_path_with_no_policy_says_what_to_pass(command, capsys):
    line = _bad_input([command, f"--policy.path={NOWHERE}"], capsys)
    assert line.startswith(f"lerobot-suture {command}: error: No trained policy at {NOWHERE}")
    assert "checkpoints/last/pretrained_model" in line


def test_assemble_names_a_missing_member(tmp_path, capsys):
    line = _bad_input(["assemble", f"--members=[{NOWHERE},{NOWHERE}]", f"--output_dir={tmp_path}"], capsys)
    assert line == f"lerobot-suture assemble: error: Policy directory {NOWHERE} does not exist."


def test_experiments_without_a_calibration_says_how_to_calibrate(tiny_policy_dir, tmp_path, capsys):
    line = _bad_input(["experiments", f"--policy.path={tiny_policy_dir}", f"--output_dir={tmp_path}"], capsys)
    assert (
        "has no O.O.D. calibration" in line
        and f"lerobot-suture calibrate --policy.path={tiny_policy_dir}" in line
    )


def test_help_lists_the_subcommands_and_a_subcommand_its_flags(capsys):
    cli_main(["--help"])
    out = capsys.readouterr().out
    assert all(f"  {name}" in out for name in SUBCOMMANDS)
    with pytest.raises(SystemExit) as exit_:
        cli_main(["demo", "--help"])
    assert exit_.value.code == 0 and "--checkpoint_every" in capsys.readouterr().out


@pytest.mark.parametrize("name", ["score-study", "benchmark-ood", "robustness-report", "assemble"])
def test_a_subcommand_of_a_distribution_not_installed_says_what_to_install(name, monkeypatch, capsys):
    """The studies and the policy plugin are distributions of their own; without them, their subcommands say
    which one to install and from where, and the others still run."""
    distribution = SUBCOMMANDS[name][0].split(".")[0]
    for module in [m for m in sys.modules if m.startswith(distribution + ".")]:
        monkeypatch.delitem(sys.modules, module)
    monkeypatch.setitem(sys.modules, distribution, None)  # as if it were not installed
    line = _bad_input([name, "--help"], capsys)
    assert f"the {distribution} distribution, which is not installed" in line and "pip install -e ./" in line


@pytest.mark.parametrize("name", ["score-study", "benchmark-ood", "robustness-report"])
def test_the_studies_subcommands_run_from_their_own_distribution(name, capsys):
    assert SUBCOMMANDS[name][0].startswith("lerobot_suture_studies.commands.")
    with pytest.raises(SystemExit) as exit_:
        cli_main([name, "--help"])
    assert exit_.value.code == 0 and "--output_dir" in capsys.readouterr().out


@pytest.mark.parametrize("name", list(SUBCOMMANDS))
def test_every_subcommand_s_help_lists_its_flags(name, capsys):
    """Each subcommand, run as a user would, answers ``--help`` with its usage and exits 0."""
    with pytest.raises(SystemExit) as exit_:
        cli_main([name, "--help"])
    out = capsys.readouterr().out
    assert exit_.value.code == 0 and "usage" in out.lower() and "--" in out, out[:500]
