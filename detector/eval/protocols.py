"""The two evaluation protocols of ``detector eval --protocol``: ``kitti`` (the KITTI object protocol,
:func:`detector.eval.kitti.evaluate`, the default) and ``open3d-ml`` (the reference's own metric, Open3D-ML's
``mAP``, :func:`detector.eval.open3d_ml.evaluate_open3d_ml`), chosen by name in one place."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Literal

from detector.eval.kitti import EvalResult, evaluate
from detector.eval.open3d_ml import Open3DMLResult, evaluate_open3d_ml, load_open3d_ml_map
from mpchair.core.errors import InputError
from mpchair.kitti import Labels

Protocol = Literal["kitti", "open3d-ml"]
PROTOCOLS: tuple[str, ...] = ("kitti", "open3d-ml")


def check_protocol(protocol: str) -> None:
    """An :class:`InputError` for an unknown protocol, or for ``open3d-ml`` when Open3D-ML is missing (checked
    before any slow work such as inference)."""
    if protocol not in PROTOCOLS:
        raise InputError(f"unknown protocol {protocol!r} (one of {', '.join(PROTOCOLS)})")
    if protocol == "open3d-ml":
        load_open3d_ml_map()


def evaluate_protocol(
    gt: Sequence[Labels],
    dt: Sequence[Labels],
    classes: Sequence[str],
    min_overlaps: Mapping[str, Sequence[float]] | None = None,
    protocol: Protocol = "kitti",
) -> EvalResult | Open3DMLResult:
    """Evaluate per-frame labels (rectified camera frame, image_2 pixels) with the named protocol."""
    check_protocol(protocol)
    if protocol == "open3d-ml":
        return evaluate_open3d_ml(gt, dt, classes, min_overlaps)
    return evaluate(gt, dt, classes, min_overlaps)
