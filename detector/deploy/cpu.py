"""Which precisions this CPU computes natively, from the instruction-set flags in ``/proc/cpuinfo``
(:func:`mpchair.core.cpu.cpu_flags`, re-exported here).

bf16 is native with AVX512-BF16 (``avx512_bf16``) or AMX-BF16 (``amx_bf16``); int8 with VNNI (``avx512_vnni``,
``avx_vnni``) or AMX-INT8 (``amx_int8``). Without them a runtime emulates the precision (OpenVINO converts bf16 to
fp32 and back; int8 GEMMs fall back to widening multiplies) and is slower than fp32, so a bench row for it would say
nothing about a deployment: :func:`skip_reason` skips it with the reason.
"""

from __future__ import annotations

from mpchair.core.cpu import cpu_flags

__all__ = ["NATIVE_FLAGS", "PRECISIONS", "RUNTIMES", "cpu_flags", "precision_flags", "skip_reason"]

RUNTIMES: tuple[str, ...] = ("torch", "onnxruntime", "openvino")
PRECISIONS: tuple[str, ...] = ("fp32", "bf16", "int8")
#: Flags that make a precision native (any one of them).
NATIVE_FLAGS: dict[str, tuple[str, ...]] = {
    "bf16": ("amx_bf16", "avx512_bf16"),
    "int8": ("amx_int8", "avx512_vnni", "avx_vnni"),
}


def precision_flags(flags: frozenset[str]) -> dict[str, list[str]]:
    """``{"bf16": [...], "int8": [...]}``: the flags of :data:`NATIVE_FLAGS` this CPU has (for the JSON record)."""
    return {p: [f for f in names if f in flags] for p, names in NATIVE_FLAGS.items()}


def skip_reason(runtime: str, precision: str, flags: frozenset[str]) -> str | None:
    """Why ``runtime`` x ``precision`` is not timed on a CPU with ``flags``, or None when it is.

    The eager torch rows run fp32 or bf16 (autocast), no int8; onnxruntime's CPU provider has no bf16 kernels; bf16
    and int8 need the CPU to compute them natively (:data:`NATIVE_FLAGS`).
    """
    if runtime not in RUNTIMES:
        raise ValueError(f"unknown runtime {runtime!r}")
    if precision not in PRECISIONS:
        raise ValueError(f"unknown precision {precision!r}")
    if precision == "fp32":
        return None
    if runtime == "torch" and precision == "int8":
        return "the eager torch model has no int8 path (int8 is a deployed runtime's)"
    if runtime == "onnxruntime" and precision == "bf16":
        return "onnxruntime's CPU execution provider has no bf16 kernels"
    if not any(f in flags for f in NATIVE_FLAGS[precision]):
        return (f"this CPU has no native {precision} ({' / '.join(NATIVE_FLAGS[precision])} missing from "
                "/proc/cpuinfo): it would be emulated, slower than fp32")
    return None
