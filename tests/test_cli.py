"""Both console scripts: every registered subcommand exists and has --help; InputError, OSError and click's usage
errors → one line + exit 2."""

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
    assert out.returncode == 2 and out.stderr.startswith("error: No such command 'nope'")


@pytest.mark.parametrize(("group", "args", "message", "command"), [
    (mpchair_cli, ["generate", "--root", "r"], "Missing option '--house'.", "generate"),
    (mpchair_cli, ["stats", "d"], "choose --density or --boxes", "stats"),
    (detector_cli, ["train", "--config", "c", "--epochs", "x"],
     "Invalid value for '--epochs': 'x' is not a valid integer.", "train"),
])
def test_usage_errors_are_one_line_and_exit_2(capsys: pytest.CaptureFixture[str], group, args, message,
                                              command) -> None:
    with pytest.raises(SystemExit) as exc:
        run_cli(group, args)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    # The hint names the program as it was started (``mpchair``, ``python -m mpchair.cli``, ...).
    assert err.startswith(f"error: {message} (see '") and err.endswith(f" {command} --help')\n")
    assert err.count("\n") == 1


def test_an_os_error_is_one_line_with_its_path_and_exit_2(capsys: pytest.CaptureFixture[str], tmp_path) -> None:
    @click.command()
    def full() -> None:
        raise OSError(28, "No space left on device", str(tmp_path / "x.bin"))

    with pytest.raises(SystemExit) as exc:
        run_cli(full, [])
    assert exc.value.code == 2
    assert capsys.readouterr().err == f"error: {tmp_path / 'x.bin'}: No space left on device\n"
