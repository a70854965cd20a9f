"""Greedy rotated NMS on exact BEV IoU (sensor frame, yaw CCW), for numpy arrays and torch tensors (CPU or GPU)."""

from __future__ import annotations

import sys

import numpy as np

# The kernel lives in iou.py next to the clip it calls: numba's cache of a kernel is invalidated only by changes
# to its own file (see mpchair/core/jit.py).
from detector.ops.iou import _nms_kernel


def _is_tensor(x) -> bool:
    # A tensor can only exist if torch is already imported; looking it up keeps numpy callers (the evaluator) from
    # paying torch's import time.
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(x, torch.Tensor)


def _float64(x) -> np.ndarray:
    """A float64 numpy copy/view on the CPU of an array or tensor."""
    if _is_tensor(x):
        import torch

        return x.detach().to("cpu", torch.float64).numpy()
    return np.asarray(x, dtype=np.float64)


def rotated_nms(boxes, scores, iou_threshold: float):
    """Greedy NMS: indices of the kept boxes, highest score first.

    ``boxes`` (N, 7) ``[x, y, z, l, w, h, yaw]`` (sensor frame, metres, yaw CCW; only the BEV rectangle is used) and
    ``scores`` (N,) are numpy arrays or torch tensors. Boxes are visited in descending score, ties in index order
    (stable sort); a box is suppressed when its exact float64 BEV IoU with an already kept box is
    ``> iou_threshold``. Returns int64 indices into the input: a numpy array for numpy input, a tensor on the
    boxes' device for torch input. The IoU runs on the CPU in float64 (meant for up to a few thousand boxes after a
    score pre-filter).
    """
    is_torch = _is_tensor(boxes)
    device = boxes.device if is_torch else None
    b = _float64(boxes)
    s = _float64(scores)
    if b.ndim != 2 or b.shape[1] != 7:
        raise ValueError(f"rotated_nms: expected (N, 7) boxes, got shape {tuple(b.shape)}")
    if s.shape != (len(b),):
        raise ValueError(f"rotated_nms: expected ({len(b)},) scores, got shape {tuple(s.shape)}")
    if np.isnan(s).any():
        raise ValueError("rotated_nms: scores contain NaN")
    order = np.argsort(-s, kind="stable")
    bev = np.ascontiguousarray(b[order][:, [0, 1, 3, 4, 6]])
    kept = order[_nms_kernel(bev, float(iou_threshold))].astype(np.int64)
    if is_torch:
        import torch

        return torch.as_tensor(kept, dtype=torch.int64, device=device)
    return kept
