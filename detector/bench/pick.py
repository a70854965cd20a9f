"""The fastest-row pick with an AP guard: a side's (dense, sparse) fastest row among those whose 3D AP stays within
:data:`AP_TOLERANCE` of their own model's eager fp32 3D AP, where both are known.

A deployment that changes the detections by more than that is another model, not a faster copy of the same one: a
headline ratio must not come from it. A row whose AP, or its model's eager fp32 AP, was not measured (a bench without
evaluations) is not guarded: it is picked on speed, as before. Used by :func:`detector.bench.run.headline_record` and
the reproduction's like-for-like table (``reproduction.deploy``), which says which rows it left out and why.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TypeVar

#: The largest |3D AP - eager fp32 3D AP| (Overall R40, AP points) a row may have and still be its side's fastest.
AP_TOLERANCE = 1.0

Row = TypeVar("Row")


def ap_exclusion(ap_3d: float | None, eager_ap_3d: float | None, tolerance: float = AP_TOLERANCE) -> str | None:
    """Why a row of 3D AP ``ap_3d`` may not be picked as its side's fastest (its model's eager fp32 gives
    ``eager_ap_3d``): a one-line reason, or None when it may (within ``tolerance``, or either AP unknown)."""
    if ap_3d is None or eager_ap_3d is None:
        return None
    delta = ap_3d - eager_ap_3d
    if abs(delta) <= tolerance:
        return None
    return (f"3D AP {ap_3d:.2f} is {delta:+.2f} from its eager fp32 {eager_ap_3d:.2f} "
            f"(more than {tolerance:g} 3D AP)")


def fastest_within_ap(rows: Sequence[Row], total_ms: Callable[[Row], float],
                      reason: Callable[[Row], str | None]) -> Row | None:
    """The row of ``rows`` with the lowest ``total_ms`` among those ``reason`` (e.g. :func:`ap_exclusion` of the
    row's APs) does not exclude; None when none is left."""
    return min((r for r in rows if reason(r) is None), key=total_ms, default=None)
