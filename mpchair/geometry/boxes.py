"""Yaw-only 3D boxes ``(N, 7)`` ``[x, y, z, l, w, h, yaw]`` in a z-up frame (sensor or world), metres / radians.

``(x, y, z)`` is the geometric centre, ``l`` the extent along the heading, ``w`` across it, ``h`` vertical; ``yaw``
is the heading, CCW about +z from +x.
"""

from __future__ import annotations

import numpy as np

# Corner signs (along l, along w, along h) in the order documented in box_corners.
_CORNER_SIGNS = np.array(
    [
        [1, -1, -1],
        [1, 1, -1],
        [-1, 1, -1],
        [-1, -1, -1],
        [1, -1, 1],
        [1, 1, 1],
        [-1, 1, 1],
        [-1, -1, 1],
    ],
    dtype=np.float64,
)


def _as_boxes(boxes: np.ndarray) -> np.ndarray:
    b = np.asarray(boxes, dtype=np.float64)
    if b.ndim != 2 or b.shape[1] != 7:
        raise ValueError(f"expected (N, 7) boxes [x, y, z, l, w, h, yaw], got shape {b.shape}")
    return b


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """The 8 corners (N,8,3) float64 of (N,7) boxes, in the boxes' frame (metres).

    Order (front = the +l / heading side; left/right as seen facing the heading)::

        top view (+z towards you)          side view from the right (+l to the right)
                  +l (heading)
                      ^                          7 ------------ 4    top:    z + h/2
            1 ------- | ------- 0                |              |
            |         |         |                |              |
     +w <-- |         o         |                3 ------------ 0    bottom: z - h/2
            |      centre       |              rear    --->    front
            2 ----------------- 3
                                               (6, 5, 2, 1 are hidden behind 7, 4, 3, 0;
                                                corner i + 4 is straight above corner i)

        0 front-right-bottom   1 front-left-bottom   2 rear-left-bottom   3 rear-right-bottom
        4 front-right-top      5 front-left-top      6 rear-left-top      7 rear-right-top

    Seen from above (+z) both faces run counter-clockwise starting at the front-right corner, so corners
    ``0..3`` are the CCW BEV polygon and corner ``i + 4`` sits above corner ``i``. (This differs from OpenPCDet's
    ``boxes_to_corners_3d`` order, whose bottom face runs clockwise from front-left.)
    """
    b = _as_boxes(boxes)
    half = b[:, None, 3:6] * 0.5 * _CORNER_SIGNS[None]  # (N,8,3) local offsets
    c, s = np.cos(b[:, 6])[:, None], np.sin(b[:, 6])[:, None]
    out = np.empty_like(half)
    out[..., 0] = c * half[..., 0] - s * half[..., 1] + b[:, None, 0]
    out[..., 1] = s * half[..., 0] + c * half[..., 1] + b[:, None, 1]
    out[..., 2] = half[..., 2] + b[:, None, 2]
    return out


def bev_polygons(boxes: np.ndarray) -> np.ndarray:
    """(N,4,2) bird's-eye-view rectangles ``(x, y)`` of (N,7) boxes, counter-clockwise from the front-right corner."""
    b = _as_boxes(boxes)
    half = b[:, None, 3:5] * 0.5 * _CORNER_SIGNS[None, :4, :2]
    c, s = np.cos(b[:, 6])[:, None], np.sin(b[:, 6])[:, None]
    out = np.empty_like(half)
    out[..., 0] = c * half[..., 0] - s * half[..., 1] + b[:, None, 0]
    out[..., 1] = s * half[..., 0] + c * half[..., 1] + b[:, None, 1]
    return out


def points_in_boxes(points: np.ndarray, boxes: np.ndarray, chunk_elements: int = 1 << 22) -> np.ndarray:
    """(N_boxes, M) bool: point ``m`` lies inside or on a face of box ``n`` (points and boxes in the same frame).

    ``points`` is (M,3) (extra columns, e.g. reflectance, are ignored). Vectorised over points and boxes; boxes are
    processed in chunks of about ``chunk_elements`` box×point pairs to bound memory.
    """
    b = _as_boxes(boxes)
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] < 3:
        raise ValueError(f"points_in_boxes expects (M, 3) points, got shape {p.shape}")
    p = p[:, :3].astype(np.float64)
    n, m = len(b), len(p)
    out = np.zeros((n, m), dtype=bool)
    if n == 0 or m == 0:
        return out
    step = max(1, chunk_elements // m)
    for start in range(0, n, step):
        bb = b[start : start + step]
        c, s = np.cos(bb[:, 6])[:, None], np.sin(bb[:, 6])[:, None]
        dx = p[None, :, 0] - bb[:, 0:1]
        dy = p[None, :, 1] - bb[:, 1:2]
        # Rotate the offset by -yaw into the box frame: along the heading, across it.
        inside = np.abs(c * dx + s * dy) <= bb[:, 3:4] * 0.5
        inside &= np.abs(c * dy - s * dx) <= bb[:, 4:5] * 0.5
        inside &= np.abs(p[None, :, 2] - bb[:, 2:3]) <= bb[:, 5:6] * 0.5
        out[start : start + step] = inside
    return out
