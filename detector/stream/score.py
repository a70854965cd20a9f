"""What each query frame is scored with, and the pooled KITTI evaluation of all query frames (sAP).

For query frame i answered by the output of frame k (:mod:`detector.stream.schedule`):

* ``raw``: the boxes as the detector emitted them, read as if they were in frame i's sensor frame (a robot that
  ignores its own motion);
* ``ego``: the boxes moved by the relative pose ``T_i^-1 T_k`` (perfect odometry; the house is static), with their
  yaw made canonical again (:func:`mpchair.geometry.canonical_yaw`, as the labels are). For ``k == i`` the boxes are
  used as they are (the relative pose is the identity), so a zero latency scores exactly the offline outputs.

Then, in frame i, predictions that match no valid chair (BEV IoU above the class's BEV threshold) are dropped when
their centre lies outside the labelled region (KITTI labels exist only there; a remembered chair behind the robot is
no false positive) or when they lie on a DontCare chair (BEV intersection / own area above the threshold with a
``label_dontcare`` box): KITTI's evaluator applies DontCare to 2D boxes only, so the 3D and BEV metrics would
otherwise count every detection of a DontCare chair as a false positive. The same rules apply to the offline outputs.

The kept boxes become 16-column KITTI result rows (:func:`detector.infer.boxes_to_results`) and all query frames of
all sequences are evaluated together by the unchanged KITTI evaluator (:func:`detector.eval.evaluate`): AP over every
ground-truth chair, 3D and BEV, R40 and R11 (:func:`evaluate_overall`). With fewer than 41 ground-truth chairs pooled,
KITTI's AP cannot reach 100 even for a perfect detector (:func:`ap_ceiling`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from detector.eval import EvalResult, evaluate, get_thresholds
from detector.eval.kitti import N_SAMPLE_PTS, ap_r11, ap_r40
from detector.infer import boxes_to_results
from detector.ops import rotated_iou_bev
from detector.stream.outputs import Output
from mpchair.geometry import canonical_yaw, in_region, invert_rigid, transform_boxes
from mpchair.kitti import Calib, Labels
from mpchair.recording.sources import Region

MODES: tuple[str, ...] = ("ego", "raw")


def moved_boxes(boxes: np.ndarray, pose_from: np.ndarray, pose_to: np.ndarray) -> np.ndarray:
    """(M,7) boxes in the sensor frame at ``pose_from`` → the sensor frame at ``pose_to`` (both (4,4) sensor → world),
    yaw canonical in ``[-pi/2, pi/2)``."""
    out = transform_boxes(boxes, invert_rigid(pose_to) @ pose_from)
    out[:, 6] = canonical_yaw(out[:, 6])
    return out


def unscored(pred: np.ndarray, region: Region, valid: np.ndarray, dontcare: np.ndarray,
             min_overlap: float) -> np.ndarray:
    """(P,) bool: predictions (P,7) that are left out of the evaluation of a frame (module docstring): those matching
    no valid box (G,7) with BEV IoU ``> min_overlap`` whose centre lies outside ``region`` or that lie on a DontCare
    box (D,7) (BEV intersection / own area ``> min_overlap``). All boxes in the frame's sensor frame.

    A prediction that matches a valid box is always scored: label files round positions to a centimetre, so a chair
    labelled just inside the region may sit just outside it.
    """
    if len(pred) == 0:
        return np.zeros(0, dtype=bool)
    drop = ~in_region(pred, region.max_abs_dz, region.max_distance, region.half_fov)
    if len(dontcare):
        iou = rotated_iou_bev(pred, dontcare)
        area_p = pred[:, 3] * pred[:, 4]
        area_d = dontcare[:, 3] * dontcare[:, 4]
        inter = iou * (area_p[:, None] + area_d[None, :]) / (1.0 + iou)  # IoU = I / (A + B - I)
        drop |= (inter / area_p[:, None] > min_overlap).any(axis=1)
    if len(valid):
        drop &= ~(rotated_iou_bev(pred, valid) > min_overlap).any(axis=1)
    return drop


def query_results(out: Output, pose_k: np.ndarray, pose_i: np.ndarray, same_frame: bool, mode: str, region: Region,
                  valid: np.ndarray, dontcare: np.ndarray, min_overlap: float, calib: Calib,
                  image_size: tuple[int, int]) -> Labels:
    """The 16-column result rows frame i is scored with, from output ``out`` of frame k (module docstring)."""
    if len(out.boxes) == 0:
        return Labels.empty(with_score=True)
    boxes = out.boxes if (mode == "raw" or same_frame) else moved_boxes(out.boxes, pose_k, pose_i)
    keep = ~unscored(boxes, region, valid, dontcare, min_overlap)
    return boxes_to_results(boxes[keep], out.scores[keep], out.names[keep], calib, image_size)


def evaluate_overall(gts: Sequence[Labels], dts: Sequence[Labels], classes: Sequence[str],
                     min_overlaps: Mapping[str, Sequence[float]]) -> tuple[EvalResult, dict]:
    """Pool ``gts`` / ``dts`` (one per query frame) through the KITTI evaluator; returns the result and its
    ``overall`` level as ``{class: {"3d": {"R40": x, "R11": y}, "bev": {...}}}`` (every ground-truth box counts)."""
    result = evaluate(gts, dts, classes, min_overlaps)
    return result, {c: {m: {v: result.overall[c][m][v] for v in ("R40", "R11")} for m in ("3d", "bev")}
                    for c in classes}


def ap_ceiling(num_gt: int) -> dict[str, float]:
    """``{"R40": x, "R11": y}``: the most any detector can score (percent, 3D or BEV) on ``num_gt`` valid ground-truth
    boxes under the KITTI protocol, which a perfect detector reaches.

    KITTI's ``get_thresholds`` takes at most one score threshold per true positive, so a perfect detector fills
    ``min(num_gt, 41)`` of the 41 precision slots (recall 0, 1/40, ..., 1) with precision 1 and the rest stay 0: below
    41 boxes that is R40 ``100 (N - 1) / 40`` and R11 ``100 (floor((N - 1) / 4) + 1) / 11``; from 41 boxes on, 100.
    The slots do not depend on the scores (ties included), only on how many true positives there are.
    """
    if num_gt <= 0:
        return {"R40": 0.0, "R11": 0.0}  # the evaluator's AP of a bucket without valid ground truth
    slots = min(len(get_thresholds(np.ones(num_gt), num_gt)), N_SAMPLE_PTS)
    precision = np.zeros(N_SAMPLE_PTS)
    precision[:slots] = 1.0
    return {"R40": float(ap_r40(precision)), "R11": float(ap_r11(precision))}
