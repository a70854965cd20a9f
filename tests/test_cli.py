"""Both console scripts: every registered subcommand exists and has --help; InputError → one line + exit 2."""

from __future__ import annotations

import subprocess
import sys

import click
import click.testing
import pytest

from detector.cli import COMMANDS as DETECTOR_COMMANDS
from detector.cli import cli as detector_cli
from mpchair.cli import COMMANDS as MPCHAIR_COMMANDS
from mpchair.cli import cli as mpchair_cli
from mpchair.clitools import run_cli
from mpchair.errors import InputError

ALL = [("mpchair", name) for name in MPCHAIR_COMMANDS] + [("detector", name) for name in DETECTOR_COMMANDS]


@pytest.mark.parametrize(("prog", "name"), ALL)
def test_every_registered_command_has_help(prog: str, name: str) -> None:
    group = mpchair_cli if prog == "mpchair" else detector_cli
    ctx = click.Context(group)
    command = group.get_command(ctx, name)
    assert command is not None, f"{prog} {name} is registered but its module is missing"
    runner = click.testing.CliRunner()
    result = runner.invoke(group, [name, "--help"])
    assert result.exit_code == 0, result.output
    assert "Usage:" in result.output and "--help" in result.output


def test_group_help_lists_every_command() -> None:
    runner = click.testing.CliRunner()
    out = runner.invoke(mpchair_cli, ["--help"]).output
    assert all(name in out for name in MPCHAIR_COMMANDS)
    out = runner.invoke(detector_cli, ["--help"]).output
    assert all(name in out for name in DETECTOR_COMMANDS)


def test_input_error_is_one_line_and_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    @click.command()
    def boom() -> None:
        raise InputError("record has 3 tokens, expected 5", "house.house", 12)

    with pytest.raises(SystemExit) as exc:
        run_cli(boom, [])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err == "error: house.house:12: record has 3 tokens, expected 5\n"


def test_console_scripts_run_as_modules() -> None:
    out = subprocess.run([sys.executable, "-m", "detector", "--help"], capture_output=True, text=True, check=False)
    assert out.returncode == 0 and "Usage:" in out.stdout
    out = subprocess.run([sys.executable, "-m", "mpchair.cli", "nope"], capture_output=True, text=True, check=False)
    assert out.returncode == 2 and "No such command" in out.stderr
