"""Bounds on what a user controls from the command line or the environment, checked before any work.

Seeds fit every random generator the project seeds (32 bits); thread and worker counts are bounded by the machine
(a few per core: ``--threads 100000`` used to end in a segfault, ``--workers`` in the out-of-memory killer); rates
and durations are finite and positive; every environment variable the CLIs read is checked once at start, with one
``error:`` line naming it (:func:`check_environment`, called by :func:`mpchair.core.clitools.run_cli`).
"""

from __future__ import annotations

import math
import os
import sys

import click

from mpchair.core.errors import InputError

#: The largest seed: numpy, torch and the project's own hashing all take 32-bit seeds.
MAX_SEED = 2**32 - 1
#: Threads or worker processes per core at most (more only adds contention; beyond, allocations fail).
PER_CORE = 4

SEED = click.IntRange(0, MAX_SEED)


def max_parallel() -> int:
    """The most threads or worker processes a command takes: :data:`PER_CORE` per core this machine has."""
    return PER_CORE * (os.cpu_count() or 1)


def machine_memory_bytes() -> int:
    """Physical memory of this machine (bytes)."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def parallel_range() -> click.IntRange:
    """``--threads`` / ``--workers``: 1 to :func:`max_parallel`."""
    return click.IntRange(1, max_parallel())


class FiniteFloat(click.ParamType):
    """A finite number above ``low`` (exclusive) and at most ``high``: NaN, infinities and 1e-300 are refused
    (``click.FloatRange`` lets NaN through: every comparison with it is false)."""

    name = "number"

    def __init__(self, low: float = 0.0, high: float = 1e9) -> None:
        self.low, self.high = low, high

    def convert(self, value, param, ctx):
        try:
            x = float(value)
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a number", param, ctx)
        if not math.isfinite(x) or not self.low < x <= self.high or x < 1e-6:  # 1e-300 Hz: a period of 1e300 s
            self.fail(f"{value!r} must be a finite number from 1e-06 to {self.high:g}", param, ctx)
        return x


def _int_env(name: str, low: int) -> int | None:
    raw = os.environ.get(name)
    if raw is None:
        return None
    try:
        value = int(raw)
    except ValueError:
        raise InputError(f"environment variable {name}={raw!r} is not a whole number") from None
    if value < low:
        raise InputError(f"environment variable {name}={value} must be >= {low}")
    return value


#: What ``MPCHAIR_EMBREE_ISA`` accepts: an Embree ISA name, or ``native`` (Embree's own choice; mpchair/scan/embree.py).
EMBREE_ISA_CHOICES = ("sse2", "sse4.2", "avx", "avx2", "avx512", "native")


def embree_isa_env() -> str | None:
    """``MPCHAIR_EMBREE_ISA`` checked (None when unset); :class:`InputError` naming the choices otherwise."""
    env = os.environ.get("MPCHAIR_EMBREE_ISA")
    if env is not None and env not in EMBREE_ISA_CHOICES:
        raise InputError(f"environment variable MPCHAIR_EMBREE_ISA={env!r}: choose one of "
                         f"{', '.join(EMBREE_ISA_CHOICES)} (or unset it)")
    return env


def check_environment() -> None:
    """:class:`InputError` for an environment variable the project reads that holds a value it cannot use:
    ``DETECTOR_GEMM`` (auto | mkl), torchrun's ``WORLD_SIZE`` / ``RANK`` / ``LOCAL_RANK`` (whole numbers, the rank
    below the world size, a world of more than one process only with torchrun's ``MASTER_ADDR`` / ``MASTER_PORT``),
    ``MPLBACKEND`` (a matplotlib backend), ``MPCHAIR_EMBREE_ISA`` (an Embree ISA name or native)."""
    embree_isa_env()
    gemm = os.environ.get("DETECTOR_GEMM")
    if gemm is not None and gemm not in ("auto", "mkl"):
        raise InputError(f"environment variable DETECTOR_GEMM={gemm!r}: choose auto or mkl (or unset it)")
    world = _int_env("WORLD_SIZE", 1)
    rank = _int_env("RANK", 0)
    local = _int_env("LOCAL_RANK", 0)
    size = world or 1
    for name, value in (("RANK", rank), ("LOCAL_RANK", local)):
        if value is not None and value >= size:
            raise InputError(f"environment variable {name}={value} must be below WORLD_SIZE={size}")
    if size > 1:
        missing = [k for k in ("MASTER_ADDR", "MASTER_PORT") if not os.environ.get(k)]
        if missing:
            raise InputError(f"WORLD_SIZE={size} but {' and '.join(missing)} not set: start distributed runs with "
                             "torchrun (torchrun --nproc-per-node=N -m detector train ...), or unset WORLD_SIZE")
        port = _int_env("MASTER_PORT", 1)
        if port is not None and port > 65535:
            raise InputError(f"environment variable MASTER_PORT={port} is not a port (1 to 65535)")
    join = os.environ.get("DETECTOR_JOIN_TIMEOUT_S")
    if join is not None:
        try:
            ok = 0 < float(join) <= 86400
        except ValueError:
            ok = False
        if not ok:
            raise InputError(f"environment variable DETECTOR_JOIN_TIMEOUT_S={join!r}: expected seconds in (0, 86400]")
    backend = os.environ.get("MPLBACKEND")
    if backend:
        _check_mpl_backend(backend)


def _check_mpl_backend(backend: str) -> None:
    def refuse(e: Exception) -> InputError:
        why = " ".join(str(e).split())
        return InputError(f"environment variable MPLBACKEND={backend!r} is not a matplotlib backend "
                          f"({why[:100]}{'...' if len(why) > 100 else ''}); unset it or choose e.g. Agg")

    try:  # matplotlib reads the variable when it is imported, and refuses a bad one there
        from matplotlib.rcsetup import validate_backend
    except ImportError:  # no matplotlib: nothing reads the variable
        return
    except ValueError as e:
        # the refused import leaves a half-made matplotlib in sys.modules: drop it, so that a caller that goes on in
        # this process (a library user, a test) imports it afresh instead of failing on attributes it never got
        for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
            del sys.modules[name]
        raise refuse(e) from None
    try:
        validate_backend(backend)
    except (ValueError, ImportError) as e:
        raise refuse(e) from None
