"""Named phases of the sparse engine's forward, so a profile says where its time goes per kind of op.

Every op of ``detector.sparse`` (and the sparse backbone's neck assembly) runs inside one of :data:`PHASES`:

- ``table``: neighbour tables and site lookups (``SiteLookup``, ``subm_table``, ``down_table``, ``up_table``), the
  GEMM forms' gather indices (``SubMTable.padded``, ``gather_index``), the rulebook's pair lists;
- ``gather``: feature rows copied into the GEMM operands (``padded_rows``, the gathers into the ``(M, K * C)``
  matrix, the transposed conv's gather of its products, the rulebook's input gathers);
- ``gemm``: the matrix products (oneDNN or ``torch.mm``);
- ``bn_relu``: BatchNorm, ReLU and bias adds on the active rows;
- ``scatter``: rows written out: the neck's levels concatenated per site, the canvas scatter (todense), the active
  mask, the rulebook's ``index_add`` / ``index_put`` / ``index_copy``.

A :class:`PhaseRecorder` active in :func:`recording` charges every stretch of wall time to the innermost open phase
(exclusive time: a table built inside a gather counts as ``table``), and the time outside any phase (Python between
ops: module calls, ``SparseTensor`` construction) to :data:`OTHER`. So the phases plus ``other`` add up to the
recorded wall time by construction, and ``other`` is what the labels miss. With no recorder active,
:func:`phase` returns one shared no-op context: a context-variable read per labelled op, nothing else (no clock, no
allocation). ``labels=True`` also opens a ``torch.profiler.record_function("sparse::<phase>")`` per phase, so a
``torch.profiler`` trace shows the same names. The recorder is a context variable, scoped to the ``with`` block (and
its thread), like ``detector.ops.gemm.gemm_backend``; nothing is global.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from contextvars import ContextVar
from typing import Any

#: The op kinds, in table order.
PHASES: tuple[str, ...] = ("table", "gather", "gemm", "bn_relu", "scatter")
#: Wall time outside every phase.
OTHER = "other"

_NO_PHASE = nullcontext()


class PhaseRecorder:
    """Exclusive wall seconds and entry counts per phase over the spans between :meth:`begin` and :meth:`end`.

    ``synchronize``: called at every phase boundary before the clock is read (``torch.cuda.synchronize`` on a GPU,
    where ops return before they finish; None on the CPU). ``labels``: also a ``torch.profiler.record_function``
    per phase.
    """

    def __init__(self, synchronize: Callable[[], None] | None = None, labels: bool = False) -> None:
        self.seconds: dict[str, float] = dict.fromkeys((*PHASES, OTHER), 0.0)
        self.calls: dict[str, int] = dict.fromkeys((*PHASES, OTHER), 0)
        self.total = 0.0
        self.synchronize = synchronize
        self.labels = labels
        self._stack: list[str] = []
        self._last = 0.0
        self._start = 0.0

    def _now(self) -> float:
        if self.synchronize is not None:
            self.synchronize()
        return time.perf_counter()

    def _charge(self, now: float) -> None:
        self.seconds[self._stack[-1] if self._stack else OTHER] += now - self._last
        self._last = now

    def begin(self) -> None:
        """Start a span (a forward): time from here is charged to ``other`` until a phase opens."""
        self._stack.clear()
        self._start = self._last = self._now()

    def end(self) -> float:
        """End the span; returns its wall seconds (also added to :attr:`total`)."""
        now = self._now()
        self._charge(now)
        self._stack.clear()
        self.total += now - self._start
        return now - self._start

    def enter(self, name: str) -> None:
        if name not in self.seconds:
            raise ValueError(f"unknown phase {name!r} (expected one of {', '.join(PHASES)})")
        self._charge(self._now())
        self._stack.append(name)
        self.calls[name] += 1

    def exit(self) -> None:
        self._charge(self._now())
        self._stack.pop()


_RECORDER: ContextVar[PhaseRecorder | None] = ContextVar("detector_sparse_phases", default=None)


class _Phase:
    """The context :func:`phase` returns while a recorder is active."""

    __slots__ = ("_label", "_name", "_recorder")

    def __init__(self, recorder: PhaseRecorder, name: str) -> None:
        self._recorder, self._name, self._label = recorder, name, None

    def __enter__(self) -> None:
        self._recorder.enter(self._name)
        if self._recorder.labels:
            import torch.profiler

            self._label = torch.profiler.record_function(f"sparse::{self._name}")
            self._label.__enter__()

    def __exit__(self, *exc: Any) -> None:
        if self._label is not None:
            self._label.__exit__(*exc)
        self._recorder.exit()


def phase(name: str) -> Any:
    """``with phase("gemm"): ...``: the block's wall time is charged to ``name`` by the active recorder (no-op
    without one). ``name`` is one of :data:`PHASES`."""
    recorder = _RECORDER.get()
    return _NO_PHASE if recorder is None else _Phase(recorder, name)


@contextmanager
def recording(recorder: PhaseRecorder) -> Iterator[PhaseRecorder]:
    """Make ``recorder`` the active one for the block (the previous one returns after it)."""
    token = _RECORDER.set(recorder)
    try:
        yield recorder
    finally:
        _RECORDER.reset(token)
