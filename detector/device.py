"""Where a model runs: the ``--device`` / ``--threads`` checks every command that runs a model shares."""

from __future__ import annotations

import torch

from mpchair.core.errors import InputError


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
