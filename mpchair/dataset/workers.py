"""A fork-based process pool that notices dead workers: ``generate``'s frames are made here when ``--workers`` > 1.

``multiprocessing.Pool`` silently replaces a worker killed by a signal (the kernel's out-of-memory killer sends
SIGKILL) and then waits forever for the chunk it held. Here the parent waits on every worker's pipe and process
sentinel at once, so a death is seen within milliseconds: the remaining workers are killed and :class:`WorkerDied`
is raised. An exception inside a worker stops the pool the same way and is re-raised in the parent. Workers are
``fork``ed, so ``initializer`` / ``initargs`` and ``fn`` are inherited, never pickled; tasks and results are.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import signal
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


def _serve(conn: Connection, fn: Callable, initializer: Callable | None, initargs: tuple) -> None:
    """Worker loop: receive chunks of tasks, send ``(True, result)`` per task or ``(False, exception)`` and stop."""
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
            p = ctx.Process(target=_serve, args=(child_end, fn, initializer, initargs), daemon=True)
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
