"""A fork-based process pool that notices dead workers: ``generate``'s frames are made here when ``--workers`` > 1.

``multiprocessing.Pool`` silently replaces a worker killed by a signal (the kernel's out-of-memory killer sends
SIGKILL) and then waits forever for the chunk it held. Here the parent waits on every worker's pipe and process
sentinel at once, so a death is seen within milliseconds: the remaining workers are killed and :class:`WorkerDied`
is raised. An exception inside a worker stops the pool the same way and is re-raised in the parent. Workers are
``fork``ed, so ``initializer`` / ``initargs`` and ``fn`` are inherited, never pickled; tasks and results are.

A worker dies with its parent, however the parent dies (SIGKILL from the out-of-memory killer included): it closes
every pipe end it inherited but its own, so its ``recv`` sees the end of its pipe once the parent is gone; on Linux
the kernel also sends it SIGKILL when the parent exits (``PR_SET_PDEATHSIG``), elsewhere a watchdog thread polls the
parent. Folder locks (:mod:`mpchair.core.lock`) are closed in every forked child, so a worker never holds one.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from multiprocessing.connection import Connection, wait
from typing import Any


class WorkerDied(Exception):
    """A worker process ended without being asked to (``pid``; ``exitcode`` as ``multiprocessing`` reports it: a
    negative number -N for signal N)."""

    def __init__(self, pid: int | None, exitcode: int | None):
        self.pid = pid
        self.exitcode = exitcode
        if exitcode is not None and exitcode < 0:
            try:
                how = f"was killed by {signal.Signals(-exitcode).name}"
            except ValueError:
                how = f"was killed by signal {-exitcode}"
            if exitcode == -signal.SIGKILL:
                how += " (the kernel's out-of-memory killer sends it when memory runs out)"
        else:
            how = f"exited with status {exitcode}"
        super().__init__(f"worker process {pid} {how}")


#: Linux's ``prctl`` option that makes the kernel signal this process when its parent exits (<linux/prctl.h>).
_PR_SET_PDEATHSIG = 1


def _die_with_parent(parent: int) -> None:
    """Make this (forked) process end when process ``parent`` ends: the kernel's parent-death signal on Linux, a
    watchdog thread polling ``getppid`` elsewhere (or where ``prctl`` cannot be called)."""
    armed = False
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
            armed = libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0
        except (OSError, AttributeError):
            armed = False
    if os.getppid() != parent:  # the parent died before the signal was armed: it will never come
        os._exit(1)
    if armed:
        return

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="parent-watchdog").start()


def _serve(conn: Connection, others: list[Connection], parent: int, fn: Callable, initializer: Callable | None,
           initargs: tuple) -> None:
    """Worker loop: receive chunks of tasks, send ``(True, result)`` per task or ``(False, exception)`` and stop.

    ``others``: the pipe ends this worker inherited from the fork (the parent's ends of every pipe so far): closed
    first, or the worker's own ``recv`` would never see the end of its pipe when ``parent`` dies."""
    _die_with_parent(parent)
    for c in others:
        with contextlib.suppress(OSError):
            c.close()
    try:
        if initializer is not None:
            initializer(*initargs)
        while (chunk := conn.recv()) is not None:
            for task in chunk:
                conn.send((True, fn(task)))
    except BaseException as e:  # noqa: BLE001 (everything goes back to the parent, which decides)
        try:
            conn.send((False, e))
        except Exception:  # an exception that does not pickle: send its text
            conn.send((False, RuntimeError(f"{type(e).__name__}: {e}")))


def imap_unordered(fn: Callable[[Any], Any], tasks: Iterable, workers: int, *, initializer: Callable | None = None,
                   initargs: tuple = (), chunksize: int = 4) -> Iterator[Any]:
    """Yield ``fn(task)`` for every task, in completion order, computed by ``workers`` forked processes.

    A task raising stops every worker and re-raises its exception here; a worker that dies raises
    :class:`WorkerDied`. Leaving the iterator early (an exception in the caller included) kills the workers.
    """
    todo = deque(tasks)
    ctx = multiprocessing.get_context("fork")
    procs, conns = [], []
    owed: dict[int, int] = {}  # worker -> results still due for the chunk it holds

    def died(k: int) -> WorkerDied:
        procs[k].join(timeout=10)  # its pipe broke: it is exiting or gone
        return WorkerDied(procs[k].pid, procs[k].exitcode)

    def hand_out(k: int) -> None:
        chunk = [todo.popleft() for _ in range(min(chunksize, len(todo)))]
        if chunk:
            try:
                conns[k].send(chunk)
            except OSError:
                raise died(k) from None
            owed[k] = len(chunk)
        else:
            owed.pop(k, None)

    try:
        for _ in range(max(1, min(workers, len(todo)))):
            parent_end, child_end = ctx.Pipe()
            p = ctx.Process(target=_serve, args=(child_end, [*conns, parent_end], os.getpid(), fn, initializer,
                                                 initargs), daemon=True)
            p.start()
            child_end.close()
            procs.append(p)
            conns.append(parent_end)
        for k in range(len(procs)):
            hand_out(k)
        by_conn = {id(c): k for k, c in enumerate(conns)}
        while owed:
            ready = wait([conns[k] for k in owed] + [p.sentinel for p in procs])
            for r in ready:
                k = by_conn.get(id(r))
                if k is None or k not in owed:
                    continue
                try:
                    ok, value = conns[k].recv()
                except (EOFError, OSError):  # died while sending, or before
                    raise died(k) from None
                if not ok:
                    raise value
                owed[k] -= 1
                if owed[k] == 0:
                    hand_out(k)
                yield value
            for k, p in enumerate(procs):
                # A worker whose pipe still holds results is read first (its error, if any, says more).
                if p.exitcode is not None and not conns[k].poll():
                    raise WorkerDied(p.pid, p.exitcode)
        for c in conns:
            with contextlib.suppress(OSError):  # a worker that died after its last result no longer matters
                c.send(None)
        for p in procs:
            p.join(timeout=10)
    finally:
        for p in procs:
            if p.exitcode is None:
                p.kill()
        for p in procs:
            p.join()
        for c in conns:
            c.close()
