"""Evaluation for ``detector``. The KITTI object protocol: AP of 2D boxes, BEV, 3D and AOS, R11 and R40, per class
and level (Easy / Moderate / Hard, and ``overall``: every GT box of the class, no size / occlusion / truncation limit),
matching the reference evaluators rule for rule except that BEV and 3D overlaps use the exact float64 IoU of
:mod:`detector.ops` (identical rotated boxes score 1). The reference's own metric: Open3D-ML's ``mAP``
(``evaluate_open3d_ml``, protocol ``open3d-ml``). ``evaluate`` takes per-frame ``mpchair.kitti.Labels`` (rectified
camera frame, image_2 pixels); ``evaluate_folders`` reads ``label_2``-style and 16-column result folders;
``report`` formats a result as a table or JSON.
"""

from detector.eval.folders import evaluate_folders, read_results
from detector.eval.kitti import (
    DEFAULT_MIN_OVERLAPS,
    DIFFICULTIES,
    LEVELS,
    METRICS,
    VARIANTS,
    EvalResult,
    evaluate,
    get_thresholds,
)
from detector.eval.open3d_ml import Open3DMLResult, evaluate_open3d_ml
from detector.eval.protocols import PROTOCOLS, evaluate_protocol
from detector.eval.report import all_ap_zero, format_table, to_json

__all__ = [
    "DEFAULT_MIN_OVERLAPS",
    "DIFFICULTIES",
    "LEVELS",
    "METRICS",
    "PROTOCOLS",
    "VARIANTS",
    "EvalResult",
    "Open3DMLResult",
    "all_ap_zero",
    "evaluate",
    "evaluate_folders",
    "evaluate_open3d_ml",
    "evaluate_protocol",
    "format_table",
    "get_thresholds",
    "read_results",
    "to_json",
]
