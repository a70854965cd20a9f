"""The KITTI object evaluation protocol for ``detector``: AP of 2D boxes, BEV, 3D and AOS, R11 and R40, per class and
difficulty (Easy / Moderate / Hard), matching the reference evaluators rule for rule except that BEV and 3D overlaps
use the exact float64 IoU of :mod:`detector.ops` (identical rotated boxes score 1). ``evaluate`` takes per-frame
``mpchair.kitti.Labels`` (rectified camera frame, image_2 pixels); ``evaluate_folders`` reads ``label_2``-style and
16-column result folders; ``report`` formats the result as a table or JSON.
"""

from detector.eval.folders import evaluate_folders, read_results
from detector.eval.kitti import DEFAULT_MIN_OVERLAPS, DIFFICULTIES, METRICS, EvalResult, evaluate, get_thresholds
from detector.eval.report import format_table, to_json

__all__ = [
    "DEFAULT_MIN_OVERLAPS",
    "DIFFICULTIES",
    "METRICS",
    "EvalResult",
    "evaluate",
    "evaluate_folders",
    "format_table",
    "get_thresholds",
    "read_results",
    "to_json",
]
