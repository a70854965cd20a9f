"""Evaluate KITTI result folders (one 16-column ``%06d.txt`` per frame, any detector's) against ``label_2``."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from detector.eval.kitti import EvalResult
from detector.eval.open3d_ml import Open3DMLResult
from detector.eval.protocols import Protocol, check_protocol, evaluate_protocol
from mpchair.core.errors import InputError
from mpchair.kitti import Labels, read_labels


def read_results(path: Path) -> Labels:
    """Read one result file; a missing file, or rows without the 16th (score) column, is an :class:`InputError`."""
    if not path.is_file():
        raise InputError("result file missing (write one per frame id, empty if nothing was detected)", path)
    labels = read_labels(path)
    if len(labels) and labels.score is None:
        raise InputError("result rows have 15 columns; evaluation needs the 16th column (score)", path)
    return labels if labels.score is not None else Labels.empty(with_score=True)


def evaluate_folders(
    label_dir: str | Path,
    result_dir: str | Path,
    ids: Sequence[str],
    classes: Sequence[str],
    min_overlaps: Mapping[str, Sequence[float]] | None = None,
    protocol: Protocol = "kitti",
) -> EvalResult | Open3DMLResult:
    """Evaluate ``result_dir/<id>.txt`` against ``label_dir/<id>.txt`` for every frame id (6-digit strings).

    Ground truth: 15 columns (rectified camera frame, image_2 pixels), DontCare rows included. Results: 16 columns,
    one file per id (an empty file means no detections). ``protocol``: ``kitti`` (:func:`detector.eval.evaluate`,
    an :class:`EvalResult`) or ``open3d-ml`` (the reference's metric, an :class:`Open3DMLResult`). Unknown classes
    without thresholds, or a missing Open3D-ML, raise :class:`InputError`.
    """
    check_protocol(protocol)
    label_dir, result_dir = Path(label_dir), Path(result_dir)
    if not ids:
        raise InputError("no frame ids to evaluate")
    for d, what in ((label_dir, "label"), (result_dir, "result")):
        if not d.is_dir():
            raise InputError(f"{what} folder not found", d)
    gt = [read_labels(label_dir / f"{i}.txt") for i in ids]
    dt = [read_results(result_dir / f"{i}.txt") for i in ids]
    try:
        return evaluate_protocol(gt, dt, classes, min_overlaps, protocol)
    except ValueError as e:  # class / threshold problems come from the user's options
        raise InputError(str(e)) from None
