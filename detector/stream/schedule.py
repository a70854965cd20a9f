"""When each detector output exists: the worker schedule in virtual time, and which output each query frame sees.

Times are int64 microseconds from the sequence start (``t_i`` of frame i), so every ``<=`` is exact.

* :func:`single_worker` (sAP's "single GPU", the default): the worker is idle at ``tau = t_0``. Whenever it is idle it
  takes the latest frame that has arrived (``t_k <= tau``) and that is newer than the last one it processed, emits its
  output at ``tau + r(k)`` and is busy until then; frames that arrive meanwhile and are superseded are never
  processed. If nothing new has arrived it waits for the next frame. It stops once ``tau`` passes the last capture
  time (no query could use a later output).
* :func:`unbounded_workers`: every frame is processed on arrival by a worker of its own: emitted at ``t_k + r(k)``.

:func:`latest_outputs` then gives, for each frame i, the output emitted last at or before ``t_i`` (-1: none yet).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np


@dataclasses.dataclass(frozen=True, eq=False)
class Schedule:
    """The outputs of one sequence in emission order: ``inputs`` (J,) frame each was computed from, ``emit_us`` (J,)
    emission times and ``latency_us`` (J,) runtimes (int64 microseconds)."""

    inputs: np.ndarray
    emit_us: np.ndarray
    latency_us: np.ndarray


def _check(r: int) -> int:
    r = int(r)
    if r < 0:
        raise ValueError(f"a latency must be >= 0 microseconds, got {r}")
    return r


def single_worker(times_us: np.ndarray, latency_us: Callable[[int], int]) -> Schedule:
    """The single-worker schedule (module docstring); ``latency_us(k)`` is frame k's runtime, called once for each
    processed frame in processing order (so a measured latency is measured only where it matters)."""
    t = np.asarray(times_us, dtype=np.int64)
    inputs, emit, lat = [], [], []
    tau = int(t[0])
    last = -1
    while tau <= t[-1]:
        k = int(np.searchsorted(t, tau, side="right")) - 1  # the latest frame with t_k <= tau
        if k <= last:  # nothing new has arrived: wait for the next frame
            if last + 1 >= len(t):
                break
            tau = int(t[last + 1])
            continue
        r = _check(latency_us(k))
        inputs.append(k)
        emit.append(tau + r)
        lat.append(r)
        tau += r
        last = k
    return Schedule(np.array(inputs, dtype=np.int64), np.array(emit, dtype=np.int64), np.array(lat, dtype=np.int64))


def unbounded_workers(times_us: np.ndarray, latency_us: Callable[[int], int]) -> Schedule:
    """Every frame processed on arrival (module docstring), outputs sorted by emission time (ties: older input first,
    so that the newer one counts as the latest)."""
    t = np.asarray(times_us, dtype=np.int64)
    lat = np.array([_check(latency_us(k)) for k in range(len(t))], dtype=np.int64)
    emit = t + lat
    order = np.lexsort((np.arange(len(t)), emit))
    return Schedule(order.astype(np.int64), emit[order], lat[order])


def latest_outputs(times_us: np.ndarray, schedule: Schedule) -> np.ndarray:
    """(N,) int64: for each frame i, the index (into the schedule) of the output emitted last with
    ``emit <= t_i``; -1 before the first emission."""
    return np.searchsorted(schedule.emit_us, np.asarray(times_us, dtype=np.int64), side="right").astype(np.int64) - 1
