"""Where a model runs and on what: the ``--device`` / ``--threads`` checks every command that runs a model shares,
and the description of the machine (CPU, threads, torch, GPU, load, allocator) that timings are recorded with."""

from __future__ import annotations

import os
import platform
from pathlib import Path

import torch

from mpchair.core.errors import InputError

#: The glibc allocator variables that can dominate CPU timings (docs/benchmarks.md), recorded with every timing.
MALLOC_ENV: tuple[str, ...] = ("MALLOC_MMAP_MAX_", "MALLOC_TRIM_THRESHOLD_")
#: The allocator setting under which freed memory is reused instead of returned to the OS after every frame.
MALLOC_REUSE: dict[str, str] = {"MALLOC_MMAP_MAX_": "0", "MALLOC_TRIM_THRESHOLD_": "68719476736"}


def use_device(device: str, threads: int | None = None) -> torch.device:
    """Check ``device`` (``cpu`` or ``cuda``, which must exist) and set torch's CPU threads; the torch device.

    ``threads`` None keeps torch's default; below 1 is an :class:`InputError`. Bad values raise before anything runs.
    """
    if threads is not None and threads < 1:
        raise InputError(f"--threads must be >= 1, got {threads}")
    if device not in ("cpu", "cuda"):
        raise InputError(f"unknown device {device!r} (cpu or cuda)")
    if device == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA device is available")
    if threads is not None:
        torch.set_num_threads(threads)
    return torch.device(device)


def cpu_model() -> str:
    """The CPU's marketing name (``/proc/cpuinfo``), or ``platform.processor()``."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def allocator_setting() -> str:
    """``reuse`` (:data:`MALLOC_REUSE` in the environment), ``default`` (none of :data:`MALLOC_ENV` set) or
    ``custom``."""
    if all(os.environ.get(k) == v for k, v in MALLOC_REUSE.items()):
        return "reuse"
    return "default" if not any(os.environ.get(k) for k in MALLOC_ENV) else "custom"


def machine_info(device: torch.device) -> dict:
    """What the timings depend on: CPU, threads, torch, GPU, load, allocator env (a JSON-ready dict)."""
    return {
        "cpu": cpu_model(),
        "logical_cpus": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "python": platform.python_version(),
        "device": str(device),
        "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
        "loadavg_1m": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "malloc_env": {k: os.environ.get(k) for k in MALLOC_ENV},
        "allocator": allocator_setting(),
    }
