"""``njit_cached``: ``numba.njit(cache=True)`` that degrades to an in-memory JIT when no cache directory is writable.

With ``cache=True`` numba stores the compiled machine code next to the source (``__pycache__/*.nbi``, ``*.nbc``) or,
when the package folder is read-only (a system-wide or container install), in ``$NUMBA_CACHE_DIR`` or the user cache
(``~/.cache/numba``). A later process loads it instead of compiling again: the detector's kernels take about 4.5 s to
compile and about 0.1 s to load. If none of those places is writable, ``numba.njit(cache=True)`` raises
``RuntimeError: cannot cache function ...: no locator available`` at decoration time, i.e. ``import detector.ops``
would fail. This wrapper then compiles without the cache (correct, only slower at the first call of every process)
and warns once, naming the fix (``NUMBA_CACHE_DIR``).

numba invalidates a cached kernel when *its own* source file changes, not when a kernel it calls from another file
does; so a kernel must only call kernels from its own file (``detector/ops/iou.py`` holds every kernel of
``detector.ops`` for that reason).

``@njit_cached(contract=True)`` lets LLVM fuse ``a * b + c`` into one fused multiply-add (numba's
``fastmath={"contract"}``, no other fast-math licence): a kernel that must reproduce torch's CPU numbers, whose GEMM
and BatchNorm kernels accumulate with FMA, needs it (``detector/models/pillar_net.py``).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any, TypeVar

import numba

F = TypeVar("F", bound=Callable[..., Any])

_warned = False


def njit_cached(fn: F | None = None, *, contract: bool = False) -> Any:
    """``numba.njit(cache=True)(fn)``, or ``numba.njit(fn)`` (with one warning per process) if nothing can be cached.

    Use bare (``@njit_cached``) or with ``contract=True`` (``@njit_cached(contract=True)``: FMA contraction allowed).
    """
    if fn is None:
        return lambda f: njit_cached(f, contract=contract)
    global _warned
    options = {"fastmath": {"contract"}} if contract else {}
    try:
        return numba.njit(cache=True, **options)(fn)
    except RuntimeError as e:
        if "no locator available" not in str(e):
            raise
        if not _warned:
            _warned = True
            warnings.warn(
                f"numba cannot cache compiled kernels (no writable __pycache__ next to {fn.__module__}, "
                "NUMBA_CACHE_DIR or user cache directory); they are compiled at first use in every process "
                "(a few seconds). Set NUMBA_CACHE_DIR to a writable folder to cache them.",
                RuntimeWarning,
                stacklevel=2,
            )
        return numba.njit(**options)(fn)
