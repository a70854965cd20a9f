"""mpchair.core.lock: a folder lock held by another process refuses a second holder, dies with its holder (SIGKILL), and
leaves no file behind; probes find exactly the held locks."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mpchair.core.errors import InputError
from mpchair.core.lock import folder_lock, held

ROOT = Path(__file__).resolve().parents[1]


def _holder(path) -> int:
    """A forked child that holds ``path`` until killed; returns its pid once it holds it."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover (child)
        try:
            with folder_lock(path, "test holder"):
                os.write(w, b"x")
                while True:
                    time.sleep(60)
        finally:
            os._exit(1)
    os.close(w)
    assert os.read(r, 1) == b"x"
    os.close(r)
    return pid


def test_a_lock_is_exclusive_dies_with_its_holder_and_leaves_no_file(tmp_path):
    lock, other = tmp_path / "run" / ".x.lock", tmp_path / "run" / ".y.lock"
    pid = _holder(lock)
    try:
        other.touch()
        assert held([lock, other, tmp_path / "missing.lock"]) == [lock]
        with pytest.raises(InputError, match=rf"^{tmp_path / 'run'}: another test holder is writing this folder "
                                             rf"\(pid {pid}\)"):
            with folder_lock(lock, "test holder"):
                pass
    finally:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
    assert lock.exists() and held([lock]) == []  # the kernel released the killed holder's lock
    with folder_lock(lock, "test holder"):
        pid_, pgid, started = lock.read_text().split()
        assert (int(pid_), int(pgid)) == (os.getpid(), os.getpgid(0)) and started.isdigit()
    assert not lock.exists()


def test_a_lock_left_to_a_dead_holders_leftovers_is_taken_over(tmp_path):
    """The holder is SIGKILLed while a process it started still holds the lock's descriptor (as a worker forked before
    this fix did, or any child given the descriptor): the pid in the file is gone, so the next run takes the folder
    over within seconds instead of being refused forever; a live holder is still refused."""
    lock = tmp_path / "run" / ".x.lock"
    code = ("import os, subprocess, sys, time\n"
            "from mpchair.core.lock import folder_lock, _HELD\n"
            "with folder_lock(sys.argv[1], 'test holder'):\n"
            "    fd = next(iter(_HELD))\n"
            "    kid = subprocess.Popen(['sleep', '60'], pass_fds=[fd])\n"
            "    print(kid.pid, flush=True)\n"
            "    time.sleep(60)\n")
    holder = subprocess.Popen([sys.executable, "-c", code, str(lock)], stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONPATH": str(ROOT)})
    leftover = int(holder.stdout.readline())
    try:
        holder.kill()
        holder.wait()
        assert held([lock]) == [lock]  # the leftover still holds the dead run's lock
        t0 = time.monotonic()
        with folder_lock(lock, "test holder"):
            assert int(lock.read_text().split()[0]) == os.getpid()
        assert time.monotonic() - t0 < 10
        assert not lock.exists()
        assert not list(lock.parent.glob("*.stale*"))
    finally:
        os.kill(leftover, signal.SIGKILL)  # a grandchild: its new parent reaps it
