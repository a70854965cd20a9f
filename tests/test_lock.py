"""mpchair.core.lock: a folder lock held by another process refuses a second holder, dies with its holder (SIGKILL), and
leaves no file behind; probes find exactly the held locks."""

from __future__ import annotations

import os
import signal
import time

import pytest

from mpchair.core.errors import InputError
from mpchair.core.lock import folder_lock, held


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
        assert lock.read_text() == f"{os.getpid()}\n"
    assert not lock.exists()
