"""The CPU's instruction-set flags, read from ``/proc/cpuinfo`` (Linux; none elsewhere).

One reader for every choice made from them: the OpenBLAS kernel pin (:mod:`mpchair.core.blas`), the Embree ISA pin
(:mod:`mpchair.scan.embree`) and the native precisions of a deployed model (:mod:`detector.deploy.cpu`). Standard
library only: ``import mpchair`` reads the flags through the BLAS pin before anything imports numpy.
"""

from __future__ import annotations

from pathlib import Path


def cpu_flags(cpuinfo: str | Path = "/proc/cpuinfo") -> frozenset[str]:
    """The instruction-set flags of the first CPU in ``cpuinfo`` (empty where the file is missing: not Linux)."""
    try:
        # line by line: the first CPU's flags come early in a file that lists every core (hundreds of KB)
        with open(cpuinfo, encoding="utf-8", errors="replace") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() == "flags":
                    return frozenset(value.split())
    except OSError:
        pass
    return frozenset()
