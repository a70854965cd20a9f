"""The one atomic-write helper: every file the project writes goes through here.

A file is written to a temporary name in its destination folder and renamed into place, so a reader (or a resumed
run after SIGKILL) never sees a half-written file.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import IO


def _create_temp(path: Path) -> tuple[int, Path]:
    """Create a new, empty temporary file beside ``path``: ``(fd, temp path)``.

    Named ``.<name>.<random>.tmp`` (so a resumed run can find and delete what a killed one left) and created with
    mode 0o666, which the kernel narrows by the umask exactly as ``open(path, "w")`` would. (``tempfile.mkstemp``
    creates 0o600 and needs a chmod and two umask calls after it, per file.) The descriptor holds an exclusive
    ``flock`` on the file while it is open: :func:`remove_dead_temps` removes only temporaries nobody holds.
    """
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0)
    for _ in range(100):
        tmp = path.with_name(f".{path.name}.{os.urandom(6).hex()}.tmp")
        try:
            fd = os.open(tmp, flags, 0o666)
        except FileExistsError:
            continue
        except FileNotFoundError:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            e.filename = str(path.parent)  # name the folder that refused, not the hidden temp name nobody asked for
            raise
        else:
            with contextlib.suppress(OSError):  # a file system without flock: the temp is simply not claimed
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return fd, tmp
    raise FileExistsError(f"no free temporary name beside {path}")


def remove_dead_temps(path: str | Path) -> list[Path]:
    """Remove the temporaries of ``path`` that a killed writer left beside it (``.<name>.<12 hex digits>.tmp``, a
    regular file whose writer no longer holds its lock); a temporary a live writer holds, and any other file, stay.
    The paths removed."""
    path = Path(path)
    name = re.compile(re.escape(f".{path.name}.") + r"[0-9a-f]{12}\.tmp")
    removed = []
    try:
        candidates = [p for p in path.parent.iterdir() if name.fullmatch(p.name)]
    except OSError:
        return removed
    for p in candidates:
        try:
            fd = os.open(p, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
        except OSError:
            continue
        try:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                continue
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # held: a live writer's
            os.unlink(p)
            removed.append(p)
        except OSError:
            continue
        finally:
            os.close(fd)
    return removed


def temp_glob(name: str) -> str:
    """Glob pattern of the temporary files :func:`atomic_open` creates for a file called ``name`` (in its folder)."""
    return f".{name}.*.tmp"


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: str = "w", fsync: bool = False) -> Iterator[IO]:
    """Open a temporary file beside ``path`` for writing; on success rename it to ``path``, on error remove it.

    An ``OSError`` raised inside (e.g. ``ENOSPC`` from a write) carries ``path`` as its ``filename`` if it had none.

    ``mode`` is ``"w"`` (text, utf-8, ``\\n`` newlines) or ``"wb"``.
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_open mode must be 'w' or 'wb', got {mode!r}")
    path = Path(path)
    fd, tmp = _create_temp(path)
    try:
        kwargs = {"encoding": "utf-8", "newline": "\n"} if mode == "w" else {}
        with os.fdopen(fd, mode, **kwargs) as f:
            yield f
            if fsync:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if isinstance(e, OSError) and e.filename is None:
            e.filename = str(path)  # a write to the open file (a full disk) names no file: name the one meant
        raise


def write_bytes(path: str | Path, data: bytes) -> None:
    """Atomically write ``data`` to ``path``."""
    with atomic_open(path, "wb") as f:
        f.write(data)


def write_text(path: str | Path, text: str) -> None:
    """Atomically write ``text`` (utf-8) to ``path``."""
    with atomic_open(path, "w") as f:
        f.write(text)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path beside ``path`` for a writer that wants a file name (not a file object); renamed to ``path``
    when the block succeeds, removed when it fails. The writer must have finished writing when the block ends."""
    path = Path(path)
    fd, tmp = _create_temp(path)
    try:  # the descriptor stays open (and the temp claimed, see _create_temp) while the writer writes by name
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    finally:
        os.close(fd)


def check_writable(path: str | Path, *, folder: bool = False) -> None:
    """Before any work: raise an :class:`~mpchair.core.errors.InputError` naming the folder when the file ``path``
    (or, with ``folder``, the folder ``path`` itself) could not be written at the end.

    The nearest folder that exists on the way (the output's own, or the ancestor its writer would create it in) must
    be a folder where a file can be created: that is tried with a probe temp file, removed at once, so the answer is
    the filesystem's (read-only mounts, ACLs, root) rather than a guess from the mode bits. Nothing else is created.
    """
    from mpchair.core.errors import InputError

    path = Path(path)
    here = path if folder else path.parent
    while not here.exists() and here != here.parent:
        here = here.parent
    if not here.is_dir():
        raise InputError(f"is not a folder, so {path} cannot be written", here)
    try:
        fd, probe = _create_temp(here / ".write-check")
    except OSError as e:
        raise InputError(f"folder not writable ({e.strerror or e}), so {path} cannot be written there; choose "
                         "another output", here) from None
    os.close(fd)
    os.unlink(probe)


def link_or_copy(src: str | Path, dst: str | Path) -> None:
    """Make ``dst`` hold ``src``'s bytes: a hard link (no second copy on disk) made under a temp name and renamed into
    place, or, where the filesystem has no hard links, an atomic copy. Nothing happens when ``dst`` already is
    ``src``'s file."""
    src, dst = Path(src), Path(dst)
    if dst.exists() and os.path.samefile(src, dst):
        return
    fd, tmp = _create_temp(dst)
    os.close(fd)
    os.unlink(tmp)  # os.link wants a free name: the one just reserved
    try:
        os.link(src, tmp)
    except OSError:
        write_bytes(dst, src.read_bytes())
        return
    try:
        os.replace(tmp, dst)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
