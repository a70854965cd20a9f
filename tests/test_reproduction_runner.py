"""The reproduction's step commands (:class:`reproduction.runner.Runner`): a failed or interrupted command ends the
experiment's CLIs with one line and the console scripts' exit status, never a traceback, and only a finished command
is logged."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from mpchair.core.clitools import run_script
from mpchair.core.errors import RunError
from reproduction.runner import Runner


def test_a_failed_command_is_one_line_and_exit_1_and_is_not_logged(tmp_path: Path, capsys) -> None:
    log = tmp_path / "commands.log"
    runner = Runner(dry_run=False, log=log)
    cmd = [sys.executable, "-c", "import sys; print('why it failed', file=sys.stderr); sys.exit(3)"]
    with pytest.raises(RunError, match=r"failed with exit status 3 .*same command resumes"):
        runner.run(cmd)
    capsys.readouterr()
    assert run_script(lambda: runner.run(cmd)) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: ") and "exit status 3" in err[-1] and "Traceback" not in "\n".join(err)
    assert not log.exists()  # only finished commands are logged


def test_an_interrupted_command_exits_130_with_a_resume_line(tmp_path: Path, capsys) -> None:
    """A step command ended by SIGINT alone (as when only the training is stopped) interrupts the experiment."""
    runner = Runner(dry_run=False, log=tmp_path / "commands.log")
    out = tmp_path / "stdout.txt"
    # SIG_DFL first: a test run started in the background inherits SIGINT ignored, and the child would then live on
    cmd = [sys.executable, "-c",
           "import os, signal; signal.signal(signal.SIGINT, signal.SIG_DFL); os.kill(os.getpid(), signal.SIGINT)"]
    assert run_script(lambda: runner.run(cmd, stdout=out)) == 130
    err = capsys.readouterr().err
    assert err.startswith("interrupted: python") and "resumes" in err and "Traceback" not in err
    assert not out.exists()  # its output file appears only for a finished command
    # a child's own exit status 130 (what `detector train` returns on Ctrl-C) reads the same way
    cmd = [sys.executable, "-c", "import sys; sys.exit(130)"]
    assert run_script(lambda: runner.run(cmd)) == 130


def test_a_finished_command_is_logged_with_its_time(tmp_path: Path) -> None:
    log = tmp_path / "commands.log"
    runner = Runner(dry_run=False, log=log)
    runner.run([sys.executable, "-c", "pass"])
    (line,) = log.read_text().splitlines()
    assert line.endswith(" -c pass") and float(line.split()[0]) >= 0.0
