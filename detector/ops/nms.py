"""Greedy rotated NMS on exact BEV IoU (sensor frame, yaw CCW), for numpy arrays and torch tensors (CPU or GPU)."""

from __future__ import annotations

import sys

import numba
import numpy as np

from detector.ops.iou import _MAX_VERTS, _inter_one


@numba.njit(cache=True)
def _nms_kernel(bev: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Keep mask over boxes already sorted by descending score; rows of ``bev`` are ``[x, y, l, w, yaw]``.

    IoUs are computed lazily, only between a kept box and boxes not yet suppressed, so the cost is
    O(kept x N) clips instead of a full N x N matrix.
    """
    n = bev.shape[0]
    keep = np.zeros(n, dtype=np.bool_)
    suppressed = np.zeros(n, dtype=np.bool_)
    p = np.empty((4, 2))
    q = np.empty((4, 2))
    buf_a = np.empty((_MAX_VERTS, 2))
    buf_b = np.empty((_MAX_VERTS, 2))
    for i in range(n):
        if suppressed[i]:
            continue
        keep[i] = True
        area_i = bev[i, 2] * bev[i, 3] if (bev[i, 2] > 0.0 and bev[i, 3] > 0.0) else 0.0
        for j in range(i + 1, n):
            if suppressed[j]:
                continue
            inter = _inter_one(bev[i, 0], bev[i, 1], bev[i, 2], bev[i, 3], bev[i, 4],
                               bev[j, 0], bev[j, 1], bev[j, 2], bev[j, 3], bev[j, 4], p, q, buf_a, buf_b)
            if inter <= 0.0:
                continue
            area_j = bev[j, 2] * bev[j, 3]
            if inter / (area_i + area_j - inter) > iou_threshold:
                suppressed[j] = True
    return keep


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
