"""Runs the reproduction's command lines as subprocesses and records them (``commands.log``, which the reports list
and time)."""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

from detector.device import MALLOC_REUSE
from mpchair.core.atomic import atomic_open
from mpchair.core.errors import RunError
from reproduction.checkout import ROOT

#: The console scripts installed next to this interpreter: the venv's ``mpchair`` / ``detector``, not PATH's.
BIN = Path(sys.executable).parent
#: glibc's allocator keeps freed memory instead of returning it to the OS (docs/benchmarks.md, "allocator reuse"): the
#: variables every timed and trained step runs under (defined once, with the machine record that reports them).
REUSE_ENV = MALLOC_REUSE


class Runner:
    """Runs and records command lines (the record goes into the report): ``commands`` holds every line this runner
    printed, ``log`` gets one ``<wall seconds> s  <line>`` per finished command."""

    def __init__(self, dry_run: bool, log: Path) -> None:
        self.dry_run = dry_run
        self.log = log
        self.commands: list[str] = []

    def run(self, args: list[str], env: dict[str, str] | None = None, stdout: Path | None = None) -> None:
        """Print ``args`` (with ``env``'s assignments and the ``> stdout`` redirection) and run it in :data:`ROOT`,
        unless a dry run; ``stdout``: the file its standard output goes to, which appears only once it succeeded."""
        prefix = " ".join(f"{k}={v}" for k, v in (env or {}).items())
        line = (prefix + " " if prefix else "") + shlex.join(args) + (f" > {stdout}" if stdout else "")
        self.commands.append(line)
        print(f"$ {line}", flush=True)
        if self.dry_run:
            return
        full_env = {**os.environ, **(env or {})}
        t = time.perf_counter()
        try:
            if stdout is not None:
                with atomic_open(stdout, "w") as f:  # only a finished command leaves its output file
                    subprocess.run(args, check=True, env=full_env, stdout=f, cwd=ROOT)
            else:
                subprocess.run(args, check=True, env=full_env, cwd=ROOT)
        except subprocess.CalledProcessError as e:
            raise failed_command(Path(args[0]).name, e.returncode) from None
        # An append, not an atomic rewrite: the log outlives this process (a resumed reproduction adds to what the cut
        # one logged), and one short line appended per finished command never leaves an earlier line half-written.
        with open(self.log, "a") as f:
            f.write(f"{time.perf_counter() - t:9.1f} s  {line}\n")


def failed_command(name: str, status: int) -> Exception:
    """What a failed step command becomes: its own output already said why, so one line naming it and its status.
    A command ended by Ctrl-C / SIGINT (status 130, or -2 for the signal) is an interruption (exit 130, the work
    folder resumes), anything else a :class:`RunError` (exit 1)."""
    if status in (130, -2):
        return KeyboardInterrupt(f"{name} was interrupted; what it saved is kept in the work folder, and the same "
                                 "command resumes")
    return RunError(f"{name} failed with exit status {status} (its messages are above); the steps before it are kept, "
                    "and the same command resumes")


def logged_commands(log: str) -> list[tuple[float, str]]:
    """(wall seconds, command line) of every finished command in a :class:`Runner`'s commands.log text."""
    return [(float(line.split()[0]), line) for line in log.splitlines() if line.strip()]
