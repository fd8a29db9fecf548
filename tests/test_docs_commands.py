"""Every ``lerobot-suture`` command the README and the docs show names a subcommand that exists and only flags
that subcommand takes (read from its own ``--help``), so a renamed or dropped flag shows here and not at a
user's desk."""

import re
from functools import cache
from pathlib import Path

import pytest

from lerobot_suture.cli import SUBCOMMANDS
from lerobot_suture.cli import main as cli_main

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
COMMAND = re.compile(r"lerobot-suture ([a-z][a-z-]*)((?:[ \t]+[^\s`|#]+)*)")


def documented_commands() -> list[tuple[str, str, str]]:
    """(document, subcommand, arguments) of each ``lerobot-suture`` command, continuation lines joined."""
    found = []
    for document in DOCUMENTS:
        text = re.sub(r"\\\n\s*", " ", document.read_text())
        for match in COMMAND.finditer(text):
            found.append((document.name, match.group(1), match.group(2)))
    return found


@cache
def help_flags(subcommand: str) -> frozenset[str]:
    """The flags ``lerobot-suture SUBCOMMAND --help`` lists."""
    import contextlib
    import io

    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        cli_main([subcommand, "--help"])
    return frozenset(re.findall(r"--([\w.]+)", out.getvalue()))


COMMANDS = documented_commands()


def test_the_docs_show_commands():
    assert len(COMMANDS) > 50 and {"README.md", "leaderboard.md"} <= {doc for doc, _, _ in COMMANDS}


@pytest.mark.parametrize(
    "document,subcommand,arguments", COMMANDS, ids=[f"{d}:{s}{a[:40]}" for d, s, a in COMMANDS]
)
def test_a_documented_command_uses_only_its_subcommand_s_flags(document, subcommand, arguments):
    if subcommand == "installed":  # prose ("lerobot-suture installed (...)"), not a command
        return
    assert subcommand in SUBCOMMANDS, f"{document}: `lerobot-suture {subcommand}` is no subcommand"
    flags = re.findall(r"(?:^|\s)--([\w.]+)", arguments)
    unknown = [flag for flag in flags if flag not in help_flags(subcommand) | {"help", "config_path"}]
    assert not unknown, f"{document}: `lerobot-suture {subcommand}` takes no {['--' + f for f in unknown]}"
