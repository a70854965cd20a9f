"""The reference's own metric: Open3D-ML's ``mAP`` (``open3d._ml3d.metrics.mAP``), called on our labels and
detections the way the Sparse PointPillars reference called it for Matterport-Chair (``run_valid`` / ``run_test`` of
its ``ObjectDetection`` pipeline: BEV then 3D, every box difficulty 0, one level).

Open3D-ML's function is called, not re-written; this module only converts the boxes into its input layout. What it
computes (its rules, summarised from ``mAP.py`` so a reader can set them beside KITTI's; ``docs/evaluation.md``):

- per frame, one IoU matrix (float32, Open3D's ``iou_bev`` / ``iou_3d`` kernels); a detection is a TP when it has
  IoU ``>=`` the threshold with a GT of its class *and* is, among all the frame's detections of that class whatever
  their score, the one with the highest IoU for some GT; every other detection is an FP (no DontCare, no 2D height
  rule); a GT of a ``similar_classes`` neighbour only keeps a detection on it from being an FP;
- thresholds: KITTI's ``get_thresholds`` rule on the TP scores (at most 41); precision at each threshold from the
  TP / FP counts of the detections scoring at least that much, max-accumulated;
- AP = ``100 * mean`` of those precisions when there are fewer than 41 thresholds (recall below 100 %: the
  missing recall is not counted as precision 0), else the 11-point mean of slots 0, 4, ..., 40.

Box layout. Open3D-ML's kernels read a box as ``(x, y_max, z, size_x, size_y, size_z, ry)``: a rectangle in the x–z
plane rotated by ``ry`` with KITTI's corner formula, spanning ``[y_max - size_y, y_max]`` vertically. The reference's
Matterport boxes had no calibration, so ``BEVBox3D.to_camera`` gave them the sensor-frame layout ``(y, z_bottom, x,
w, h, l, yaw)``: the BEV rectangle is exactly the sensor box (l along the heading, yaw CCW), but each box spans
``[z_bottom - h, z_bottom]``, i.e. its height is measured *downward* from its bottom face. Its 3D IoU therefore
differs from the true one when a detection's bottom and height both differ from its GT's. We keep that: the input is
the camera box of :func:`detector.ops.iou.camera_boxes` ``[x, y, z, l, h, w, ry]`` (y the bottom, y down) with
``y + h`` in the ``y_max`` slot, which spans ``[y, y + h]`` — below the bottom face, as the reference's boxes did.
The BEV rectangles are the same up to the camera↔sensor isometry, so every IoU equals the reference's wherever
camera y is the sensor's -z (every mpchair dataset), up to float32 rounding; ``tests/test_eval_open3d_ml.py`` checks
this against ``BEVBox3D.to_dicts`` on sensor-frame boxes. (The reference's KITTI runs went through Open3D-ML's
KITTI reader, whose camera boxes span upward: the true 3D IoU. Only the 3D metric can differ.)

Needs Open3D with its ML part (``pip install 'open3d-cpu[ml]'``, the project's ``open3d`` extra); without it the
protocol is an :class:`mpchair.core.errors.InputError`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from detector.eval.kitti import check_inputs, resolve_min_overlaps
from detector.ops.iou import camera_boxes
from mpchair.core.errors import InputError
from mpchair.kitti import Labels

PROTOCOL = "open3d-ml"

#: ``similar_classes`` of the reference's KITTI configs (``{Van: Car, Person_sitting: Pedestrian}``; its Matterport
#: configs pass ``{}``), lower case like every name here. Open3D-ML looks up ``similar_classes.get(evaluated
#: class)``, so this mapping only acts when Van or Person_sitting is the evaluated class; for Car and Chair it is
#: the same as ``{}``, as it was in the reference.
REFERENCE_SIMILAR_CLASSES: Mapping[str, str] = {"van": "car", "person_sitting": "pedestrian"}

#: Open3D-ML metrics: BEV (``bev=True``) and 3D, the two the reference logged.
O3D_METRICS: tuple[str, ...] = ("bev", "3d")


@dataclasses.dataclass(frozen=True)
class Open3DMLResult:
    """Open3D-ML ``mAP`` per class (percent, 0–100): ``ap[cls]["bev" | "3d"]``; one level (every box difficulty 0).

    ``num_gt[cls]`` counts the class's GT boxes (names case-insensitive); ``min_overlaps[cls]`` is (bev, 3d);
    ``warnings`` names classes without GT (AP 0).
    """

    classes: tuple[str, ...]
    min_overlaps: dict[str, tuple[float, float]]
    num_gt: dict[str, int]
    ap: dict[str, dict[str, float]]
    num_frames: int
    warnings: tuple[str, ...] = ()

    def to_json_dict(self) -> dict:
        """``{"protocol": "open3d-ml", "<Class>": {"bev": x, "3d": y}, "num_gt": {"<Class>": n}}``."""
        out: dict = {"protocol": PROTOCOL}
        for cls in self.classes:
            out[cls] = dict(self.ap[cls])
        out["num_gt"] = dict(self.num_gt)
        return out


def load_open3d_ml_map() -> Callable:
    """Open3D-ML's ``mAP`` function (imported without its torch / TensorFlow pipelines); an
    :class:`InputError` with the install command when Open3D-ML is missing or does not load."""
    try:
        from open3d._ml3d.metrics import mAP
    except (ImportError, OSError) as e:  # OSError: open3d present but a shared library (e.g. libusb) missing
        raise InputError(f"the {PROTOCOL} protocol needs Open3D-ML ({e}); install it with: "
                         "pip install 'open3d-cpu[ml]' (the project's open3d extra)") from None
    return mAP


def open3d_ml_frame(labels: Labels) -> dict[str, np.ndarray]:
    """One frame in Open3D-ML's evaluation layout (what ``BEVBox3D.to_dicts`` gave it in the reference).

    ``bbox`` (N, 7) float64 ``[x, y + h, z, l, h, w, ry]``: the camera box (rectified camera frame, ``y`` the bottom,
    y down, metres) with its height hanging below the bottom face, as the reference's calibration-free boxes did
    (module docstring); ``label`` (N,) lower-case class names; ``difficulty`` (N,) zeros (no calibration, hence
    difficulty 0); ``score`` (N,) when ``labels`` has scores. DontCare rows stay; Open3D-ML drops every row that is
    not of an evaluated class before it computes an overlap.
    """
    box = camera_boxes(labels.location, labels.dims_hwl, labels.rotation_y)
    box[:, 1] += box[:, 4]  # y_max slot: the box spans [y, y + h], below its bottom face (reference layout)
    out = {
        "bbox": box,
        "label": np.char.lower(labels.names),
        "difficulty": np.zeros(len(labels)),
    }
    if labels.score is not None:
        out["score"] = np.asarray(labels.score, dtype=np.float64).reshape(-1)
    return out


def evaluate_open3d_ml(
    gt: Sequence[Labels],
    dt: Sequence[Labels],
    classes: Sequence[str],
    min_overlaps: Mapping[str, Sequence[float]] | None = None,
) -> Open3DMLResult:
    """Evaluate detections with Open3D-ML's ``mAP`` exactly as the reference did; AP in percent.

    Same inputs as :func:`detector.eval.evaluate` (``gt[f]`` / ``dt[f]`` per frame, rectified camera frame,
    detections with scores; classes case-insensitive, result keys spelled as given). Thresholds: the BEV and 3D
    entries of :data:`detector.eval.DEFAULT_MIN_OVERLAPS` / ``min_overlaps`` (Chair 0.5, Car 0.7, as the reference's
    ``overlaps``), matched with ``>=``. Calls ``mAP(pred, target, classes, difficulties=[0], min_overlap, bev,
    similar_classes=REFERENCE_SIMILAR_CLASSES)`` once for BEV and once for 3D.
    """
    classes = check_inputs(gt, dt, classes)
    thr = resolve_min_overlaps(classes, min_overlaps)
    m_ap = load_open3d_ml_map()
    keys = [c.lower() for c in classes]
    target = [open3d_ml_frame(g) for g in gt]
    pred = [open3d_ml_frame(d if d.score is not None else Labels.empty(with_score=True)) for d in dt]
    ap: dict[str, dict[str, float]] = {c: {} for c in classes}
    for k, metric in enumerate(O3D_METRICS):
        # A class without GT divides by a zero count inside sample_thresholds (numpy: inf, no TP, AP 0).
        with np.errstate(divide="ignore", invalid="ignore"):
            values = m_ap(pred, target, keys, [0], [thr[c][1 + k] for c in classes], bev=metric == "bev",
                          similar_classes=dict(REFERENCE_SIMILAR_CLASSES))
        for i, c in enumerate(classes):
            ap[c][metric] = float(values[i, 0, 0])
    num_gt = {c: int(sum(np.count_nonzero(t["label"] == key) for t in target)) for c, key in zip(classes, keys)}
    return Open3DMLResult(classes=classes, min_overlaps={c: (thr[c][1], thr[c][2]) for c in classes},
                          num_gt=num_gt, ap=ap, num_frames=len(gt),
                          warnings=tuple(f"{c}: 0 GT boxes; AP is 0" for c in classes if num_gt[c] == 0))
