"""Output-folder locks: one process at a time writes a dataset shard or a training run.

A lock is an exclusive ``fcntl.flock`` on a small file in the folder (``.generate-0-of-1.lock``, ``.train.lock``).
The kernel releases it when the holding process exits, however it exits (SIGKILL included), so a killed run never
blocks the command that resumes it: a lock file left on disk means nothing by itself. The holder removes the file when
it is done (a re-check of the file's identity after locking makes that safe against a process that opened the old
file just before) and writes its pid, process group and start time into it for a second process.

A forked child would share the lock (``flock`` belongs to the open file, which a fork duplicates): a worker left
running after its parent was killed would block every later run. So every forked child closes the lock descriptors
it inherited (``os.register_at_fork``), and a second process that finds the lock busy checks its holder: when the
pid written in the file is gone (or is another process now: its start time differs) and the lock stays held a moment
longer, the lock is held only by what the dead run left behind, and is taken over (a new lock file replaces the
stale one; the leftovers keep the old, unlinked one).
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

#: Lock descriptors this process holds. Module state on purpose: a fork copies them into the child whatever code
#: forks (a worker pool, a DataLoader), and only this module knows which descriptors are locks.
_HELD: set[int] = set()


def _close_inherited() -> None:
    """In a forked child: close the lock descriptors inherited from the parent (closing, never unlocking: an unlock
    would release the parent's lock too)."""
    for fd in _HELD:
        with contextlib.suppress(OSError):
            os.close(fd)
    _HELD.clear()


os.register_at_fork(after_in_child=_close_inherited)

#: How long a lock whose holder is gone may stay held (its forked leftovers dying) before it is taken over.
_STALE_WAIT_S = 3.0


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
    _HELD.discard(fd)
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)  # while still locked: a process that opened it meanwhile sees the change and retries
    os.close(fd)


def _start_time(pid: int) -> str:
    """The start time of process ``pid`` in clock ticks since boot (``/proc/PID/stat`` field 22), or "" where
    unknown: with the pid it names one process, never a later one that reuses the pid."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text(encoding="ascii", errors="replace")
    except OSError:
        return ""
    fields = stat.rpartition(")")[2].split()  # the command name (field 2) may hold spaces and parentheses
    return fields[19] if len(fields) > 19 else ""


def _stamp() -> bytes:
    """What a holder writes into its lock file: ``pid pgid start-time``."""
    pid = os.getpid()
    return f"{pid} {os.getpgid(0)} {_start_time(pid)}\n".encode("ascii")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process: alive
        return True
    return True


def _holder(path: Path) -> tuple[int | None, int | None, bool]:
    """``(pid, pgid, alive)`` of the process whose stamp ``path`` holds; ``alive`` is True when unknown (no stamp:
    the holder may not have written it yet), False when that pid has ended or now names another process."""
    try:
        words = path.read_text(encoding="ascii").split()
    except (OSError, UnicodeDecodeError):
        return None, None, True
    if not words or not all(w.isdigit() for w in words):
        return None, None, True
    pid = int(words[0])
    pgid = int(words[1]) if len(words) > 1 else None
    if not _alive(pid):
        return pid, pgid, False
    started = words[2] if len(words) > 2 else ""
    now = _start_time(pid)
    return pid, pgid, not (started and now and started != now)


def _group_alive(pgid: int | None) -> bool:
    if pgid is None or pgid <= 1:
        return False
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _take_over(path: Path) -> int | None:
    """Lock ``path`` once its recorded holder is gone: while processes of the holder's group live, wait up to
    :data:`_STALE_WAIT_S` for them (forked children dying with it) to release it; then replace the stale file by a
    new one and lock that. None when a live holder appeared meanwhile."""
    deadline = time.monotonic() + (_STALE_WAIT_S if _group_alive(_holder(path)[1]) else 0.5)
    while time.monotonic() < deadline:
        fd = _acquire(path, wait=False)
        if fd is not None:
            return fd
        if _holder(path)[2]:
            return None
        time.sleep(0.1)
    if _holder(path)[2]:  # another process took it over meanwhile
        return None
    stale = path.with_name(f"{path.name}.stale{os.getpid()}")
    with contextlib.suppress(FileNotFoundError):
        os.rename(path, stale)  # atomic: a process that opened the old file re-checks its identity and retries
        os.unlink(stale)
    return _acquire(path, wait=False)


@contextlib.contextmanager
def folder_lock(path: str | Path, what: str, *, folder: str | Path | None = None) -> Iterator[None]:
    """Hold the lock file ``path`` (created, with its folder, if missing) for the ``with`` block, then remove it.

    When another process holds it, raise :class:`InputError` naming the folder (``folder``, default the lock's own)
    and ``what`` holds it (e.g. ``"mpchair generate"``), without waiting.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = _acquire(path, wait=False)
    if fd is None and not _holder(path)[2]:
        fd = _take_over(path)
    if fd is None:
        pid = _holder(path)[0]
        who = "" if pid is None else f" (pid {pid})"
        raise InputError(f"another {what} is writing this folder{who}; wait for it to finish or stop it "
                         "(a killed run leaves no lock behind)", path.parent if folder is None else folder)
    _HELD.add(fd)
    try:
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, _stamp(), 0)
        except OSError as e:  # a full disk: a write to a descriptor names no file, so name the folder
            raise OSError(e.errno, e.strerror, str(path.parent if folder is None else folder)) from None
        yield
    finally:
        _release(path, fd)


@contextlib.contextmanager
def wait_lock(path: str | Path) -> Iterator[None]:
    """Hold the lock file ``path``, waiting for other holders, then remove it (for short critical sections)."""
    path = Path(path)
    fd = _acquire(path, wait=True)
    _HELD.add(fd)
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
