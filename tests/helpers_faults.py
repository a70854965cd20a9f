"""Fault injection for tests/test_faults.py: SIGKILL at a chosen file rename, a run in a forked child, folder trees.

Every file the project writes is renamed into place by ``mpchair.core.atomic`` with ``os.replace``, so "SIGKILL just
before rename N" (or before the rename onto a path ending in a given suffix) reaches every state a killed run can leave
on disk: the renamed files before it, the temp file of this one. The hook replaces ``os.replace`` in the process that
runs the command (a forked child, or ``python tests/helpers_faults.py SUFFIX -- detector ...``); production code is
not changed. A folder swapped in whole (:func:`mpchair.core.owned.replace_folder`) is exchanged by ``renameat2``,
not ``os.replace``: :func:`kill_at_swap` kills at that swap instead.

    python tests/helpers_faults.py eval/epoch_001/metrics.json -- detector train --config ...
    python tests/helpers_faults.py --stop .frames/000002.json -- mpchair generate ...   (stopped there instead)
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path


def _under(dst, folder: Path | None) -> bool:
    """Whether ``dst`` lies in ``folder`` (None: anywhere). Renames elsewhere (numba's on-disk cache writing its
    index on a cold cache, say) are not the run's and are neither counted nor killed at."""
    return folder is None or Path(os.path.abspath(dst)).is_relative_to(Path(os.path.abspath(folder)))


def kill_at_replace(when: int | str, folder: Path | None = None, sig: int = signal.SIGKILL) -> None:
    """From now on, send this process ``sig`` (SIGKILL) just before the ``when``-th ``os.replace`` into ``folder``
    (1-based) or before the first whose destination ends with ``when`` (a path suffix). With SIGSTOP the process
    waits there, stopped, for the test to signal it (a Ctrl-C at that exact moment), then goes on."""
    real = os.replace
    count = 0

    def replace(src, dst, *args, **kwargs):
        nonlocal count
        if _under(dst, folder):
            count += 1
            if count == when or (isinstance(when, str) and str(dst).replace(os.sep, "/").endswith(when)):
                os.kill(os.getpid(), sig)
        return real(src, dst, *args, **kwargs)

    os.replace = replace


def kill_at_swap(moment: str, sig: int = signal.SIGKILL) -> None:
    """From now on, send this process ``sig`` at ``moment`` of :func:`mpchair.core.owned.replace_folder`'s swap of a
    complete staged folder with the old output: ``"before"`` / ``"after"`` the ``renameat2(RENAME_EXCHANGE)``, or
    ``"between"`` the two renames of the fallback used where the file system lacks the exchange (made to lack it here:
    the old folder is renamed aside, then the process dies before the new one is renamed in)."""
    from mpchair.core import owned

    real = owned._exchange
    if moment == "between":
        owned._exchange = lambda a, b: False  # the answer of a file system without RENAME_EXCHANGE
        rename = os.rename
        count = 0

        def second_rename(src, dst, *args, **kwargs):
            nonlocal count
            count += 1
            if count == 2:  # out -> .out.old<pid> was the first
                os.kill(os.getpid(), sig)
            return rename(src, dst, *args, **kwargs)

        os.rename = second_rename
        return

    def exchange(a, b):
        if moment == "before":
            os.kill(os.getpid(), sig)
        done = real(a, b)
        if moment == "after":
            os.kill(os.getpid(), sig)
        return done

    owned._exchange = exchange


def count_replaces(fn: Callable[[], object], folder: Path | None = None) -> int:
    """How many ``os.replace`` calls into ``folder`` ``fn()`` makes (in this process)."""
    real = os.replace
    count = 0

    def replace(src, dst, *args, **kwargs):
        nonlocal count
        count += _under(dst, folder)
        return real(src, dst, *args, **kwargs)

    os.replace = replace
    try:
        fn()
    finally:
        os.replace = real
    return count


def run_forked(fn: Callable[[], object]) -> int:
    """Run ``fn()`` in a forked child and wait; returns the raw wait status (the child exits 0 when ``fn`` returns,
    1 when it raises)."""
    pid = os.fork()
    if pid == 0:  # pragma: no cover (child)
        code = 1
        try:
            fn()
            code = 0
        finally:
            os._exit(code)
    return os.waitpid(pid, 0)[1]


@contextlib.contextmanager
def mounted_tmpfs(folder: Path, size: str) -> Iterator[Path]:
    """A tmpfs of ``size`` (``700k``) mounted on the new folder ``folder`` (a real ENOSPC), unmounted afterwards;
    the test is skipped where mounting is not allowed (it needs root with CAP_SYS_ADMIN)."""
    import pytest

    folder.mkdir()
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)], capture_output=True,
                         text=True)
    if res.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root with CAP_SYS_ADMIN): {res.stderr.strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], check=True)


def tree(path: Path) -> dict[str, bytes]:
    """Every file under ``path`` (hidden ones, temp and lock files included) → its bytes."""
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def main(argv: list[str]) -> None:
    """``[--stop] SUFFIX -- mpchair|detector ARGS...``: run the CLI, SIGKILLed (with ``--stop``: stopped with
    SIGSTOP) before the rename onto ``*SUFFIX``."""
    sep = argv.index("--")
    stop = argv[0] == "--stop"
    kill_at_replace(argv[1 if stop else 0], sig=signal.SIGSTOP if stop else signal.SIGKILL)
    prog, args = argv[sep + 1], argv[sep + 2 :]
    if prog == "detector":
        from detector.cli import main as cli
    else:
        from mpchair.cli import main as cli
    cli(args)


if __name__ == "__main__":
    main(sys.argv[1:])
