"""Sensor-frame boxes ↔ KITTI camera labels, projection of boxes into image_2, and the image_2 field of view.

Frames: the sensor / KITTI LiDAR frame (x forward, y left, z up, metres; boxes by geometric centre) and the KITTI
rectified camera-0 frame (x right, y down, z forward, metres; labels by bottom centre), linked by
``X_rect = R0_rect · Tr_velo_to_cam · X_sensor``; image_2 pixels come from ``P2 · X_rect``.
"""

from __future__ import annotations

import math

import numpy as np

from mpchair.geometry.boxes import box_corners
from mpchair.geometry.frames import transform_points, wrap_angle
from mpchair.kitti.calib import Calib
from mpchair.kitti.labels import Labels

#: Box edges as corner index pairs (corner order of :func:`box_corners`): bottom ring, top ring, verticals.
BOX_EDGES: np.ndarray = np.array(
    [[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6], [3, 7]]
)
BOX_EDGES.setflags(write=False)

#: Projective depth (metres) below which box parts count as behind the camera and are clipped away.
NEAR_PLANE = 1e-3


def _as_boxes(boxes: np.ndarray) -> np.ndarray:
    b = np.asarray(boxes, dtype=np.float64)
    if b.ndim != 2 or b.shape[1] != 7:
        raise ValueError(f"expected (N, 7) boxes [x, y, z, l, w, h, yaw], got shape {b.shape}")
    return b


def boxes_to_kitti_camera(boxes: np.ndarray, calib: Calib) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sensor-frame (N,7) boxes → KITTI label fields in the rectified camera frame.

    Returns ``location`` (N,3) bottom centre (rectified camera, metres), ``dims_hwl`` (N,3) ``h, w, l``,
    ``rotation_y`` (N,) ``= -yaw - pi/2`` and ``alpha`` (N,) ``= rotation_y - atan2(x, z)`` of ``location``, both
    wrapped to ``[-pi, pi)``. The yaw formula is exact when ``R0_rect · Tr_velo_to_cam`` is a pure axis swap (what
    mpchair writes); on real KITTI calibrations it ignores the small sensor tilt, like OpenPCDet.
    """
    b = _as_boxes(boxes)
    bottom = b[:, :3].copy()
    bottom[:, 2] -= b[:, 5] * 0.5
    location = transform_points(bottom, calib.velo_to_rect())
    dims_hwl = b[:, [5, 4, 3]].copy()
    rotation_y = wrap_angle(-b[:, 6] - math.pi / 2)
    alpha = wrap_angle(rotation_y - np.arctan2(location[:, 0], location[:, 2]))
    return location, dims_hwl, rotation_y, alpha


def kitti_camera_to_boxes(
    location: np.ndarray, dims_hwl: np.ndarray, rotation_y: np.ndarray, calib: Calib
) -> np.ndarray:
    """KITTI label fields (rectified camera frame, bottom centre, ``h w l``, ``rotation_y``) → (N,7) sensor boxes.

    The inverse of :func:`boxes_to_kitti_camera`: centre = ``(R0_rect·Tr)^-1 · location`` raised by ``h/2`` along
    sensor +z, ``yaw = -rotation_y - pi/2`` wrapped to ``[-pi, pi)``.
    """
    location = np.asarray(location, dtype=np.float64).reshape(-1, 3)
    dims = np.asarray(dims_hwl, dtype=np.float64).reshape(-1, 3)
    ry = np.asarray(rotation_y, dtype=np.float64).reshape(-1)
    if not len(location) == len(dims) == len(ry):
        raise ValueError(f"length mismatch: {len(location)} locations, {len(dims)} dims, {len(ry)} rotations")
    out = np.empty((len(location), 7))
    out[:, :3] = transform_points(location, calib.rect_to_velo())
    out[:, 2] += dims[:, 0] * 0.5
    out[:, 3] = dims[:, 2]
    out[:, 4] = dims[:, 1]
    out[:, 5] = dims[:, 0]
    out[:, 6] = wrap_angle(-ry - math.pi / 2)
    return out


def labels_to_boxes(labels: Labels, calib: Calib) -> np.ndarray:
    """(N,7) sensor-frame boxes of every row of ``labels`` (filter out DontCare rows first: they carry no 3D box)."""
    return kitti_camera_to_boxes(labels.location, labels.dims_hwl, labels.rotation_y, calib)


def project_boxes_to_image(
    boxes: np.ndarray, calib: Calib, image_size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """2D image_2 boxes of (N,7) sensor-frame boxes, and their truncation.

    The 8 corners go through ``P2 · R0_rect · Tr_velo_to_cam``. Parts of a box behind the camera are cut off first:
    every edge is clipped against the plane ``depth = NEAR_PLANE`` (projective depth, the third row of the
    projection), so a box straddling the camera plane still gets the 2D box of its visible part. Returns

    * ``bbox`` (N,4) float64 ``[left, top, right, bottom]`` pixels, clipped to ``[0, W-1] × [0, H-1]`` like
      OpenPCDet; ``[0, 0, 0, 0]`` for a box wholly behind the camera;
    * ``truncation`` (N,) in ``[0, 1]``: the fraction of the unclipped projected 2D box's area outside
      ``[0, W-1] × [0, H-1]``; 1.0 for boxes wholly behind the camera or outside the image.

    ``image_size`` is ``(W, H)`` of this frame's image_2 (sizes vary per frame).
    """
    b = _as_boxes(boxes)
    W, H = image_size
    n = len(b)
    corners = box_corners(b)  # (N,8,3) sensor frame
    M = calib.velo_to_image()
    uvw = corners @ M[:, :3].T + M[:, 3]  # (N,8,3) homogeneous pixels; affine in the corner, so edges map to edges
    a = uvw[:, BOX_EDGES[:, 0]]  # (N,12,3)
    c = uvw[:, BOX_EDGES[:, 1]]
    wa, wc = a[..., 2], c[..., 2]
    crosses = (wa > NEAR_PLANE) != (wc > NEAR_PLANE)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(crosses, (NEAR_PLANE - wa) / (wc - wa), 0.0)
    cut = a + t[..., None] * (c - a)  # where an edge pierces the near plane
    cand = np.concatenate([uvw, cut], axis=1)  # (N,20,3): visible corners + edge cuts span the visible part
    valid = np.concatenate([uvw[..., 2] > NEAR_PLANE, crosses], axis=1)
    w = np.where(valid, cand[..., 2], 1.0)
    u = np.where(valid, cand[..., 0] / w, np.nan)
    v = np.where(valid, cand[..., 1] / w, np.nan)
    any_valid = valid.any(axis=1)
    bbox = np.zeros((n, 4))
    truncation = np.ones(n)
    if not any_valid.any():
        return bbox, truncation
    k = np.flatnonzero(any_valid)
    u0, u1 = np.nanmin(u[k], axis=1), np.nanmax(u[k], axis=1)
    v0, v1 = np.nanmin(v[k], axis=1), np.nanmax(v[k], axis=1)
    cu0, cu1 = np.clip(u0, 0, W - 1), np.clip(u1, 0, W - 1)
    cv0, cv1 = np.clip(v0, 0, H - 1), np.clip(v1, 0, H - 1)
    bbox[k] = np.stack([cu0, cv0, cu1, cv1], axis=1)
    area = (u1 - u0) * (v1 - v0)
    inside = (cu1 - cu0) * (cv1 - cv0)
    with np.errstate(divide="ignore", invalid="ignore"):
        frac_out = np.where(area > 0, 1.0 - inside / np.where(area > 0, area, 1.0), 0.0)
    # A degenerate (zero-area) projection is fully outside unless its point / segment lies inside the image.
    degenerate_out = (u1 < 0) | (u0 > W - 1) | (v1 < 0) | (v0 > H - 1)
    frac_out = np.where(area > 0, frac_out, degenerate_out.astype(np.float64))
    truncation[k] = np.clip(frac_out, 0.0, 1.0)
    return bbox, truncation


def fov_mask(points: np.ndarray, calib: Calib, image_size: tuple[int, int]) -> np.ndarray:
    """(N,) bool: sensor-frame points in front of camera 0 (rectified z > 0) that project inside image_2.

    Inside means ``0 <= u < W`` and ``0 <= v < H`` (OpenPCDet's ``FOV_POINTS_ONLY`` rule); ``image_size`` is
    ``(W, H)`` of this frame.
    """
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] < 3:
        raise ValueError(f"fov_mask expects (N, 3) points, got shape {p.shape}")
    W, H = image_size
    rect = transform_points(p[:, :3].astype(np.float64), calib.velo_to_rect())
    uvw = rect @ calib.P2[:, :3].T + calib.P2[:, 3]
    front = (rect[:, 2] > 0) & (uvw[:, 2] > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = uvw[:, 0] / uvw[:, 2]
        v = uvw[:, 1] / uvw[:, 2]
    return front & (u >= 0) & (u < W) & (v >= 0) & (v < H)
