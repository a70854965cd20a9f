"""Where a model runs and on what: the ``--device`` / ``--threads`` checks every command that runs a model shares,
and the description of the machine (CPU, threads, torch, GPU, load, allocator) that timings are recorded with."""

from __future__ import annotations

import math
import os
import platform
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import torch

from mpchair.core.errors import InputError

#: The glibc allocator variables that can dominate CPU timings (docs/benchmarks.md), recorded with every timing.
MALLOC_ENV: tuple[str, ...] = ("MALLOC_MMAP_MAX_", "MALLOC_TRIM_THRESHOLD_")
#: The allocator setting under which freed memory is reused instead of returned to the OS after every frame.
MALLOC_REUSE: dict[str, str] = {"MALLOC_MMAP_MAX_": "0", "MALLOC_TRIM_THRESHOLD_": "68719476736"}
#: OpenMP's idle threads sleep at once instead of spin-waiting: on a machine whose cores other jobs keep busy, a
#: spinning thread waits for one that is not scheduled, and the sparse model's many small parallel ops suffer most.
OMP_PASSIVE: dict[str, str] = {"OMP_WAIT_POLICY": "PASSIVE"}


def rerun_under(env: Mapping[str, str], argv: Sequence[str]) -> None:
    """Return when every variable of ``env`` already has its value here; else replace this process by ``python
    argv...`` (this interpreter) with ``env`` added to its environment.

    glibc's allocator (:data:`MALLOC_REUSE`) and OpenMP (:data:`OMP_PASSIVE`) read their variables only when the
    process starts, so a tool that offers them as flags re-runs itself: setting ``os.environ`` would be too late.
    """
    if all(os.environ.get(k) == v for k, v in env.items()):
        return
    sys.stdout.flush()
    os.execve(sys.executable, [sys.executable, *argv], {**os.environ, **env})


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


def usable_cores() -> int:
    """The logical CPUs this process may run on (its affinity mask where the OS has one, else ``os.cpu_count()``)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def load_1m() -> float:
    """The 1-minute load average (runnable processes, machine-wide), 0.0 where the OS has none."""
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else 0.0


def free_cores(cores: int, load: float) -> int:
    """The cores another process leaves free: ``cores`` minus the 1-minute ``load``, rounded, at least 1."""
    return max(1, min(cores, math.floor(cores - load + 0.5)))


def oversubscription_warning(threads: int, cores: int, load: float) -> str | None:
    """One line when ``threads`` plus the 1-minute ``load`` (rounded to whole cores, as :func:`free_cores`: an idle
    machine's load of 0.3 fills no core) exceed ``cores`` (the threads then share cores with other work and wait on
    each other: the sparse path's many small ops suffer most), else None."""
    if threads <= free_cores(cores, load):
        return None
    return (f"--threads {threads} + load {load:.1f} exceed the {cores} cores: timings will be slower than on an idle "
            f"machine, the sparse backbone's most (use --threads {free_cores(cores, load)} or a quiet machine)")


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


@dataclass(frozen=True)
class Machine:
    """What timings depend on, recorded with every one (the ``machine`` of ``detector bench --json``, of ``detector
    stream-eval``'s latency log, of the tools' JSON): the CPU's name and logical CPUs, torch's CPU threads, the torch
    and Python versions, the torch device and its GPU's name (None on the CPU), the 1-minute load average when it was
    taken, the glibc allocator variables (:data:`MALLOC_ENV`, None: unset) and :func:`allocator_setting`.

    The one definition of that record: :meth:`to_json` writes it, :meth:`from_json` reads it back (a key a file lacks
    reads as None / empty)."""

    cpu: str
    logical_cpus: int | None
    torch_threads: int | None
    torch: str | None
    python: str | None = None
    device: str | None = None
    gpu: str | None = None
    loadavg_1m: float | None = None
    malloc_env: Mapping[str, str | None] = field(default_factory=dict)
    allocator: str | None = None

    @classmethod
    def here(cls, device: torch.device) -> Machine:
        """This machine now, running on ``device``."""
        return cls(cpu=cpu_model(), logical_cpus=os.cpu_count(), torch_threads=torch.get_num_threads(),
                   torch=torch.__version__, python=platform.python_version(), device=str(device),
                   gpu=torch.cuda.get_device_name(device) if device.type == "cuda" else None,
                   loadavg_1m=os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
                   malloc_env={k: os.environ.get(k) for k in MALLOC_ENV}, allocator=allocator_setting())

    def to_json(self) -> dict[str, Any]:
        """The record as JSON data, in field order."""
        return {f.name: dict(self.malloc_env) if f.name == "malloc_env" else getattr(self, f.name)
                for f in fields(self)}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Machine:
        """The record of :meth:`to_json`'s data (other keys, such as a bench's additions, are ignored)."""
        known = {f.name: d.get(f.name) for f in fields(cls) if f.name not in ("cpu", "malloc_env")}
        return cls(cpu=d.get("cpu") or "", malloc_env=dict(d.get("malloc_env") or {}), **known)


MACHINE_KEYS: tuple[str, ...] = tuple(f.name for f in fields(Machine))


def machine_info(device: torch.device) -> dict[str, Any]:
    """:meth:`Machine.here` as JSON data (the ``machine`` entry a timing's JSON embeds)."""
    return Machine.here(device).to_json()


# --- what the CUDA path needs beyond the CPU path (issue 32) ------------------------------------------------------
# On the CPU every helper here is a cheap no-op or a fixed answer, so callers need no ``if device.type == "cuda"``
# of their own.

#: cuBLAS reproducibility setting torch asks for before it lets a deterministic run use cuBLAS (CUDA >= 10.2).
CUBLAS_WORKSPACE = ":4096:8"


def synchronize(device: torch.device | str) -> None:
    """Wait until every kernel queued on ``device`` has finished (CUDA); a no-op on the CPU, whose ops return done.

    CUDA kernels run asynchronously: a ``time.perf_counter`` stamp without this measures the launches, not the work.
    """
    dev = torch.device(device)
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def synced_clock(device: torch.device | str) -> float:
    """A timer stamp (seconds, ``time.perf_counter``) taken after :func:`synchronize`: the difference of two stamps
    covers the device work queued between them."""
    synchronize(device)
    return time.perf_counter()


def autocast_dtype(device: torch.device | str) -> torch.dtype:
    """The reduced precision ``torch.autocast`` should use on ``device``: bfloat16 on the CPU and on GPUs that compute
    it natively (NVIDIA Ampere and newer), float16 on older GPUs (e.g. the paper's Turing 2080 Ti).

    float16 training also needs a ``torch.amp.GradScaler`` (its range underflows small gradients); bfloat16 does not
    (see :func:`needs_grad_scaler`).
    """
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_bf16_supported(including_emulation=False):
        return torch.float16
    return torch.bfloat16


def needs_grad_scaler(dtype: torch.dtype) -> bool:
    """Whether mixed-precision training in ``dtype`` needs loss scaling: float16 only (5 exponent bits)."""
    return dtype == torch.float16


def pin_memory(device: torch.device | str) -> bool:
    """Whether host batches bound for ``device`` should sit in page-locked memory (``DataLoader(pin_memory=...)``):
    True for CUDA, where a pinned tensor's ``.to(device, non_blocking=True)`` overlaps the copy with queued kernels;
    False for the CPU (pinning would be a copy for nothing)."""
    return torch.device(device).type == "cuda" and torch.cuda.is_available()


def reset_peak_memory(device: torch.device | str) -> None:
    """Start a new peak for :func:`peak_memory_bytes`: CUDA's allocator peak on a GPU; on the CPU the process's peak
    resident set (Linux ``VmHWM``, reset through ``/proc/self/clear_refs``; where that is refused the peak keeps
    counting from the process start)."""
    dev = torch.device(device)
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
        return
    try:
        with open("/proc/self/clear_refs", "w") as f:  # a kernel control file, not data: no atomic write
            f.write("5")
    except OSError:
        pass


def peak_memory_bytes(device: torch.device | str) -> int | None:
    """Peak memory since :func:`reset_peak_memory` (bytes): on a GPU the most its tensors held at once
    (``torch.cuda.max_memory_allocated``); on the CPU the process's peak resident set (``VmHWM``, tensors and
    everything else). None where the platform does not say (no ``/proc``)."""
    dev = torch.device(device)
    if dev.type == "cuda":
        return int(torch.cuda.max_memory_allocated(dev))
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024  # the kernel reports kB
    except OSError:
        pass
    return None


class deterministic:  # lower case: used like a function, ``with deterministic(): ...``
    """Context manager: torch's deterministic algorithms on, for bit-identical reruns on CUDA too.

    On the CPU the project's kernels are deterministic anyway. On CUDA the float ``index_add_`` of the sparse
    convolutions and the backward of every gather (``features[rows]``) accumulate with atomics, whose order differs
    from run to run; under this context torch uses its sorted, deterministic versions (slower), cuDNN picks
    deterministic algorithms, and an op without a deterministic version raises ``RuntimeError`` instead of running.
    cuBLAS needs ``CUBLAS_WORKSPACE_CONFIG`` set before its first use in the process: set here to
    :data:`CUBLAS_WORKSPACE` unless it is set already. The previous mode is restored on exit.
    """

    def __enter__(self) -> deterministic:
        import os

        self._previous = (torch.are_deterministic_algorithms_enabled(),
                          torch.is_deterministic_algorithms_warn_only_enabled())
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", CUBLAS_WORKSPACE)
        torch.use_deterministic_algorithms(True)
        return self

    def __exit__(self, *exc: object) -> None:
        enabled, warn_only = self._previous
        torch.use_deterministic_algorithms(enabled, warn_only=warn_only)
