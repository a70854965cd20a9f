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
from collections.abc import Iterator
from pathlib import Path

from mpchair.errors import InputError

_BUSY = (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES)


def _acquire(path: Path, wait: bool) -> int | None:
    """A descriptor of ``path`` holding its exclusive lock, or None when another process holds it (``wait=False``)."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except OSError as e:
            os.close(fd)
            if e.errno in _BUSY and not wait:
                return None
            raise
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


def is_locked(path: str | Path) -> bool:
    """True when a process holds the lock file ``path`` (a missing file is not locked).

    Probes by taking the lock for an instant: a process starting to take it at that very instant is refused, so call
    it only where that process would conflict with the caller anyway.
    """
    try:
        fd = os.open(path, os.O_RDWR | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as e:
        if e.errno in _BUSY:
            return True
        raise
    finally:
        os.close(fd)
    return False
