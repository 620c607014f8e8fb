"""The CLI's help pages: every command documents itself without placeholder types on flags."""

from __future__ import annotations

import re

import pytest
from typer.testing import CliRunner

from mewa_bench.cli import app

COMMANDS = [["evaluate"], ["record"], ["view"], ["leaderboard"], ["generate"], ["train"], ["info"],
            ["suites", "verify"], ["datasets", "download"], ["datasets", "pack"], ["datasets", "build"], ["serve"], ["serve", "token", "create"],
            ["serve", "worker"], ["submit"], ["status"], ["compare"], ["results", "convert"]]


@pytest.mark.parametrize("command", COMMANDS, ids=" ".join)
def test_help_shows_flags_without_a_value_type(command: list[str]) -> None:
    result = CliRunner().invoke(app, [*command, "--help"], env={"COLUMNS": "160"})
    assert result.exit_code == 0, result.output
    option_lines = [line for line in result.output.splitlines() if re.match(r"^│ +--", line)]
    assert option_lines, result.output
    for line in option_lines:
        if not line.lstrip("│ ").startswith("--help"):  # click's own help flag keeps typer's rendering
            assert "<bool>" not in line, line
    usage = next(line for line in result.output.splitlines() if "Usage:" in line)
    assert not re.search(r"\{[a-z_]+\}", usage), usage  # arguments are named in capitals, as in most CLIs
