"""One OpenBLAS kernel on every x86-64 machine, so that the same seed gives the same bytes on AVX2 and AVX-512 CPUs.

numpy's bundled OpenBLAS picks its GEMM kernels from the CPU at load time (Haswell kernels on an AVX2-only CPU,
SkylakeX ones with AVX-512). The kernels sum in different orders, so float64 products such as the synthetic houses'
transforms differ in the last bits, and those bits decide some of ``mpchair synth``'s seeded choices: on an AVX-512
EPYC, ``synth --houses 12 --seed 0`` wrote three different houses than on an AVX2 one (the accuracy study's record,
docs/results-data/accuracy, was made on the AVX2 machine). Pinning ``OPENBLAS_CORETYPE=Haswell`` (the AVX2 + FMA
kernels, which every AVX-512 CPU also runs) before numpy is first imported makes both machines write the same houses;
``tests/test_blas_kernel.py`` checks the record's houses byte for byte.

The pin is set in ``os.environ`` (so worker processes inherit it) only where it can take effect and is safe: Linux
x86-64 CPUs with AVX2 and FMA, numpy not imported yet, ``OPENBLAS_CORETYPE`` unset, and ``MPCHAIR_KEEP_BLAS_KERNEL``
unset (set it to 1 to keep OpenBLAS's own choice). Elsewhere (Arm, macOS's Accelerate, CPUs without AVX2) results
may differ in the last bits from the x86 ones; docs/generate.md, "Determinism", says so.
"""

from __future__ import annotations

import os
import platform
import sys

from mpchair.core.cpu import cpu_flags  # stdlib only: safe before numpy loads

#: The kernel family pinned on x86-64: OpenBLAS's AVX2 + FMA kernels.
KERNEL = "Haswell"


def pin_openblas_kernel() -> str | None:
    """Set ``OPENBLAS_CORETYPE`` to :data:`KERNEL` where the module docstring says; returns the kernel pinned (or
    already chosen by the user), None where nothing was set."""
    if "OPENBLAS_CORETYPE" in os.environ:
        return os.environ["OPENBLAS_CORETYPE"]
    if os.environ.get("MPCHAIR_KEEP_BLAS_KERNEL") or "numpy" in sys.modules:
        return None
    if sys.platform != "linux" or platform.machine() not in ("x86_64", "AMD64"):
        return None
    if not {"avx2", "fma"} <= cpu_flags():
        return None
    os.environ["OPENBLAS_CORETYPE"] = KERNEL
    return KERNEL


def openblas_kernel() -> str | None:
    """The kernel numpy's OpenBLAS runs with in this process (e.g. ``Haswell``, ``SkylakeX``), None if unknown."""
    try:
        from threadpoolctl import threadpool_info
    except ImportError:
        return None
    import numpy  # noqa: F401  (loads OpenBLAS so that threadpoolctl sees it)

    for info in threadpool_info():
        if info.get("internal_api") == "openblas":
            return info.get("architecture")
    return None
