"""Inference: a trained model over a KITTI-format split → KITTI result files (16 columns) → KITTI-protocol AP.

Detections come out of the model as sensor-frame boxes ``[x, y, z, l, w, h, yaw]``; they are written in the frame's
own label frame through its calib (:func:`mpchair.geometry.boxes_to_kitti_camera`: bottom centre in the rectified
camera frame, ``h w l``, ``rotation_y``, ``alpha = rotation_y - atan2(x, z)``), with the 2D box of the projected 3D
box clipped to that frame's real image size (:func:`mpchair.geometry.project_boxes_to_image`) — the KITTI
difficulty rules need sensible 2D boxes even for BEV and 3D AP. ``truncated`` / ``occluded`` are written as -1, like
the common frameworks. Every frame of the split gets a file, empty when nothing was detected.
"""

from __future__ import annotations

import re
import shutil
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from detector.checkpoint import load_model
from detector.config import ExperimentConfig, load_experiment
from detector.data import Frame, KittiDataset
from detector.data.experiment import augment_options, open_split
from detector.data.pipeline import make_eval_sample
from detector.device import use_device
from detector.models import Detections
from detector.pretrained import is_pretrained
from mpchair.core.atomic import write_text
from mpchair.core.owned import check_replaceable, clear_leftovers, replace_folder, work_dir
from mpchair.geometry import boxes_to_kitti_camera, project_boxes_to_image
from mpchair.kitti import Calib, Labels, frame_paths, read_image_size, write_labels

RESULTS_SUBDIR = "data"  # result files go to OUT/data/<id>.txt (OpenPCDet's final_result/data layout)
#: The writer named in the result folder's ownership marker (:mod:`mpchair.core.owned`): ``detector eval`` and the
#: evaluations during ``detector train`` write the folder alike.
RESULTS_COMMAND = "detector eval"


def detections_to_labels(
    det: Detections, frame: Frame, classes: tuple[str, ...], image_size: tuple[int, int]
) -> Labels:
    """One frame's detections as 16-column KITTI result rows (rectified camera frame of ``frame.calib``).

    ``det.boxes`` (M,7) sensor frame, ``det.scores`` (M,), ``det.labels`` (M,) index into ``classes``;
    ``image_size`` ``(W, H)`` of the frame's image_2.
    """
    boxes = det.boxes.detach().cpu().to(torch.float64).numpy().reshape(-1, 7)
    scores = det.scores.detach().cpu().to(torch.float64).numpy().reshape(-1)
    labels = det.labels.detach().cpu().numpy().reshape(-1)
    names = np.array([classes[int(k)] for k in labels], dtype=str)
    return boxes_to_results(boxes, scores, names, frame.calib, image_size)


def boxes_to_results(boxes: np.ndarray, scores: np.ndarray, names: np.ndarray, calib: Calib,
                     image_size: tuple[int, int]) -> Labels:
    """16-column KITTI result rows of (M,7) sensor-frame ``boxes`` with ``scores`` (M,) and class ``names`` (M,),
    in the rectified camera frame of ``calib``; 2D boxes projected and clipped to ``image_size`` ``(W, H)``."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    n = len(boxes)
    if n == 0:
        return Labels.empty(with_score=True)
    location, dims_hwl, rotation_y, alpha = boxes_to_kitti_camera(boxes, calib)
    bbox, _ = project_boxes_to_image(boxes, calib, image_size)
    return Labels(
        names=np.asarray(names, dtype=str),
        truncated=np.full(n, -1.0),
        occluded=np.full(n, -1, dtype=np.int64),
        alpha=alpha,
        bbox=bbox,
        dims_hwl=dims_hwl,
        location=location,
        rotation_y=rotation_y,
        score=np.asarray(scores, dtype=np.float64),
    )


def predict_split(
    model: nn.Module, frames: KittiDataset, cfg: ExperimentConfig, *, device: torch.device | str = "cpu",
    batch_size: int | None = None, progress: bool = True,
) -> Iterator[tuple[Frame, Detections]]:
    """Run ``model`` (put in eval mode here) over every frame of ``frames``, yielding ``(frame, detections)``."""
    options = augment_options(cfg)
    bs = batch_size or cfg.eval.batch_size
    model.eval()
    ids = frames.ids
    with torch.no_grad(), tqdm(total=len(ids), desc=f"infer {frames.split}", unit="frame", disable=not progress,
                                leave=False) as bar:
        for start in range(0, len(ids), bs):
            chunk = [frames.load(fid) for fid in ids[start : start + bs]]
            points = [torch.from_numpy(make_eval_sample(f, options).points).to(device) for f in chunk]
            dets = model.predict(points)
            yield from zip(chunk, dets)
            bar.update(len(chunk))


@torch.no_grad()
def recalibrate_batchnorm(
    model: nn.Module, frames: KittiDataset, cfg: ExperimentConfig, *, device: torch.device | str = "cpu",
    batch_size: int | None = None, progress: bool = True,
) -> int:
    """Re-estimate every BatchNorm's running mean/variance as the plain average of batch statistics over ``frames``
    ("precise BN"); returns the number of batches. Leaves the model in eval mode.

    The reference BN momentum (0.01) makes the running statistics an average over the last few hundred steps of
    changing weights; after a short run they still remember their initial values (mean 0, variance 1) and the eval-mode
    network is far from the trained one. Averaging fresh batch statistics of the final weights (forward passes in
    train mode without gradients, no augmentation) fixes that without touching any weight.
    """
    options = augment_options(cfg)
    bs = batch_size or cfg.train.batch_size
    norms = [m for m in model.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
    momenta = [m.momentum for m in norms]
    for m in norms:
        m.reset_running_stats()
        m.momentum = None  # cumulative average over the batches below
    model.train()
    n = 0
    try:
        for start in tqdm(range(0, len(frames), bs), desc="recalibrate BN", unit="batch", disable=not progress,
                          leave=False):
            chunk = [frames.load(fid) for fid in frames.ids[start : start + bs]]
            model([torch.from_numpy(make_eval_sample(f, options).points).to(device) for f in chunk])
            n += 1
    finally:
        for m, momentum in zip(norms, momenta):
            m.momentum = momentum
        model.eval()
    return n


#: Metrics file of each evaluation protocol in the output folder.
METRICS_FILES = {"kitti": "metrics.json", "open3d-ml": "metrics_open3d_ml.json"}


def evaluate_model(
    model: nn.Module, cfg: ExperimentConfig, data_dir: str | Path, split: str, out_dir: str | Path | None, *,
    device: torch.device | str = "cpu", progress: bool = True, protocol: str = "kitti",
):
    """Predict ``split`` of ``data_dir`` with ``model``, write result files under ``out_dir/data`` and the metrics
    (``metrics.json``; ``metrics_open3d_ml.json`` for ``protocol="open3d-ml"``) if ``out_dir`` is given, and return
    the result against the split's labels (DontCare included): a :class:`detector.eval.EvalResult` (``kitti``) or
    :class:`detector.eval.Open3DMLResult` (``open3d-ml``, the reference's metric).

    Result files are written to a temporary folder and renamed into place only when every frame succeeded, so a
    failure leaves no partial result folder.
    """
    from detector.eval.protocols import check_protocol, evaluate_protocol

    check_protocol(protocol)  # before the inference: an unknown protocol or a missing Open3D-ML fails at once
    if out_dir is not None:
        check_results_dir(out_dir)

    frames = KittiDataset(data_dir, split, classes=cfg.data.classes, name_map=dict(cfg.data.rename),
                          fov_crop=cfg.data.fov_crop)
    gts: list[Labels] = []
    dts: list[Labels] = []
    for frame, det in predict_split(model, frames, cfg, device=device, progress=progress):
        size = frame.image_size or read_image_size(frame_paths(frames.root, frame.frame_id).image_2)
        dts.append(detections_to_labels(det, frame, cfg.data.classes, size))
        gts.append(frame.gt)
    min_overlaps = {c: (t, t, t) for c, t in zip(cfg.eval.classes, cfg.eval.iou_thresholds)}
    result = evaluate_protocol(gts, dts, cfg.eval.classes, min_overlaps, protocol)
    if out_dir is not None:
        write_results(out_dir, frames.ids, dts)
        write_text(Path(out_dir) / METRICS_FILES[protocol], _json(result))
    return result


def _json(result) -> str:
    from detector.eval import to_json

    return to_json(result) + "\n"


def _legacy_results(folder: Path) -> set[str] | None:
    """The files of a result folder written before ownership markers: nothing but ``<id>.txt`` files (None
    otherwise)."""
    names = [p.name for p in folder.iterdir()]
    ok = all(re.fullmatch(r"[0-9]+\.txt", n) and (folder / n).is_file() and not (folder / n).is_symlink()
             for n in names)
    return set(names) if ok else None


def check_results_dir(out_dir: str | Path) -> None:
    """Before any inference: :class:`InputError` unless ``OUT/data`` may be (re)written: missing, empty, or result
    files this command wrote (a folder holding anything else, such as a user's measurements, is never replaced)."""
    check_replaceable(Path(out_dir) / RESULTS_SUBDIR, RESULTS_COMMAND, legacy=_legacy_results,
                      option="--out (its data/ folder is replaced)")


def write_results(out_dir: str | Path, ids: list[str], labels: list[Labels]) -> Path:
    """Write ``OUT/data/<id>.txt`` for every id (16 columns; empty files for frames without detections).

    The folder is filled under a hidden work name and swapped in at the end (an older ``data`` folder this command
    wrote is replaced; any other is refused, :func:`check_results_dir`). A killed run's work folder is removed.
    """
    out = Path(out_dir)
    final = out / RESULTS_SUBDIR
    check_results_dir(out)
    clear_leftovers(final, RESULTS_COMMAND, legacy=_legacy_results, extra=(f".{RESULTS_SUBDIR}.tmp",))
    stage = work_dir(out, f".{RESULTS_SUBDIR}.work", RESULTS_COMMAND)
    try:
        for fid, lab in zip(ids, labels):
            write_labels(stage / f"{fid}.txt", lab)
        replace_folder(stage, final, RESULTS_COMMAND, legacy=_legacy_results)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return final


def default_results_dir(checkpoint: str | Path, split: str) -> Path:
    """Where ``detector eval --checkpoint`` writes without ``--out``: ``<checkpoint folder>/<checkpoint name>_<split>``
    (``runs/dense/last.pt``, ``val`` → ``runs/dense/last_val``; packaged weights ``pretrained:sparse`` →
    ``pretrained_sparse_val`` in the working folder)."""
    if is_pretrained(checkpoint):
        return Path(f"{str(checkpoint).replace(':', '_')}_{split}")
    ckpt = Path(checkpoint)
    return ckpt.parent / f"{ckpt.stem}_{split}"


def evaluate_checkpoint(
    config_path: str | Path,
    data_dir: str | Path,
    checkpoint: str | Path,
    split: str = "val",
    out_dir: str | Path | None = None,
    *,
    device: str = "cpu",
    threads: int | None = None,
    recalibrate_bn_split: str | None = None,
    progress: bool = True,
    protocol: str = "kitti",
):
    """``detector eval --config --data --checkpoint``: inference on ``split`` + result files + evaluation with
    ``protocol`` (``kitti``, or ``open3d-ml``: the reference's metric; see :func:`evaluate_model`).

    ``recalibrate_bn_split`` (e.g. ``"train"``): first re-estimate the BatchNorm statistics on that split
    (:func:`recalibrate_batchnorm`; useful after short runs, off by default as in the reference).

    Writes ``OUT/data/<id>.txt`` (16-column KITTI results, one per frame id of the split) and ``OUT/metrics.json``
    (``OUT/metrics_open3d_ml.json`` for ``open3d-ml``); ``out_dir`` defaults to ``<checkpoint folder>/<checkpoint
    name>_<split>``. Returns the :class:`detector.eval.EvalResult` (or ``Open3DMLResult``). Everything is validated
    (config, checkpoint, split, protocol) before anything is written.
    """
    from detector.eval.protocols import check_protocol

    check_protocol(protocol)
    use_device(device, threads)
    cfg = load_experiment(config_path)
    model = load_model(cfg, checkpoint, device)
    # A missing folder, split or frame file fails here, before any output (a progress bar included).
    open_split(cfg, data_dir, split).check()
    if recalibrate_bn_split is not None:
        frames = open_split(cfg, data_dir, recalibrate_bn_split)
        frames.check()
        recalibrate_batchnorm(model, frames, cfg, device=device, progress=progress)
    if out_dir is None:
        out_dir = default_results_dir(checkpoint, split)
    return evaluate_model(model, cfg, data_dir, split, out_dir, device=device, progress=progress, protocol=protocol)
