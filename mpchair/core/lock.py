"""Output-folder locks: one process at a time writes a dataset shard or a training run.

A lock is an exclusive ``fcntl.flock`` on a small file in the folder (``.generate-0-of-1.lock``, ``.train.lock``).
The kernel releases it when the holding process exits, however it exits (SIGKILL included), so a killed run never
blocks the command that resumes it: a lock file left on disk means nothing by itself. The holder removes the file when
it is done (a re-check of the file's identity after locking makes that safe against a process that opened the old
file just before) and writes its pid into it for the error message of a second process.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import time
from collections.abc import Iterator
from pathlib import Path

from mpchair.core.errors import InputError

_BUSY = (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES)


#: Tries before a held lock counts as busy: a probe (:func:`held`) holds a lock for microseconds, a run for its life.
_TRIES = 5


def _acquire(path: Path, wait: bool) -> int | None:
    """A descriptor of ``path`` holding its exclusive lock, or None when another process holds it (``wait=False``)."""
    busy = 0
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except OSError as e:
            os.close(fd)
            if e.errno not in _BUSY or wait:
                raise
            busy += 1
            if busy == _TRIES:
                return None
            time.sleep(0.05)
            continue
        try:
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)  # the holder removed the file between our open and our lock: lock the new one


def _release(path: Path, fd: int) -> None:
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)  # while still locked: a process that opened it meanwhile sees the change and retries
    os.close(fd)


def _holder(path: Path) -> str:
    try:
        pid = path.read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError):
        return ""
    return f" (pid {pid})" if pid.isdigit() else ""


@contextlib.contextmanager
def folder_lock(path: str | Path, what: str) -> Iterator[None]:
    """Hold the lock file ``path`` (created, with its folder, if missing) for the ``with`` block, then remove it.

    When another process holds it, raise :class:`InputError` naming the folder and ``what`` holds it (e.g.
    ``"mpchair generate"``), without waiting.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = _acquire(path, wait=False)
    if fd is None:
        raise InputError(f"another {what} is writing this folder{_holder(path)}; wait for it to finish or stop it "
                         "(a killed run leaves no lock behind)", path.parent)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
        yield
    finally:
        _release(path, fd)


@contextlib.contextmanager
def wait_lock(path: str | Path) -> Iterator[None]:
    """Hold the lock file ``path``, waiting for other holders, then remove it (for short critical sections)."""
    path = Path(path)
    fd = _acquire(path, wait=True)
    try:
        yield
    finally:
        _release(path, fd)


def _probe(path: Path) -> bool:
    """Whether ``path`` is locked right now (taking its lock for an instant when it is not)."""
    try:
        fd = os.open(path, os.O_RDWR | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return False
    except OSError as e:
        if e.errno not in _BUSY:
            raise
        return True
    finally:
        os.close(fd)


def held(paths: list[Path]) -> list[Path]:
    """The lock files among ``paths`` that some process holds (a missing file is not held).

    Probes by taking each lock for an instant, in a few rounds a moment apart: only a lock held through every round
    counts, so two probes never take each other for a holder, and :func:`folder_lock` (which retries the same way)
    never takes a probe for one.
    """
    busy = list(paths)
    for i in range(_TRIES):
        busy = [p for p in busy if _probe(p)]
        if not busy:
            break
        if i + 1 < _TRIES:
            time.sleep(0.05)
    return busy
