"""Keep freed memory in the process's heap (glibc) for processes that allocate and free the same large arrays often.

A generated frame allocates and frees a dozen arrays of 0.1-4 MB (ray directions, masks, hits). glibc's malloc
serves blocks above its mmap threshold with fresh ``mmap`` pages and returns them with ``munmap`` on free, and trims
the heap top, so every frame paid tens of thousands of page faults in the kernel: with the setting below one
process spent 24.2 instead of 28.7 ms of CPU per frame (``tools/bench_generate.py`` conditions, system time
1.57 s → 0.21 s over 300 frames). It is the same setting as ``MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=...``
(``docs/benchmarks.md``), applied at run time to the processes that make frames (``mpchair generate`` and its
workers). The cost: the process keeps its peak heap until it exits.
"""

from __future__ import annotations

import ctypes

_M_TRIM_THRESHOLD = -1  # glibc <malloc.h>
_M_MMAP_MAX = -4


def keep_freed_memory() -> bool:
    """Make glibc's malloc serve every block from the heap (no mmap) and never trim it; False where not glibc."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # not glibc (macOS, Windows, musl without mallopt)
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, 2**31 - 1))
