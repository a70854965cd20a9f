"""Global augmentations and filters on one sample (points + boxes, both in the sensor frame).

Every function is pure: it takes ``points`` (N,C) float32 with ``x, y, z`` in the first three columns (sensor frame,
metres; extra columns such as reflectance ride along unchanged) and ``boxes`` (M,7) ``[x, y, z, l, w, h, yaw]``,
and returns new arrays. Random choices come from an explicit ``numpy.random.Generator``. The global transforms
(flip, rotation about z, uniform scaling) are similarities applied to points and boxes alike, so a point inside a box
stays inside it.
"""

from __future__ import annotations

import math

import numpy as np

from mpchair.geometry import wrap_angle


def random_flip_y(
    points: np.ndarray, boxes: np.ndarray, rng: np.random.Generator, probability: float = 0.5
) -> tuple[np.ndarray, np.ndarray, bool]:
    """Mirror the scene across the sensor's x-z plane (``y → -y``, ``yaw → -yaw``) with ``probability``.

    The forward axis is kept, so a front-facing scan (camera FOV) stays in front. Returns (points, boxes, flipped).
    One draw from ``rng`` whatever the outcome, so later draws do not depend on it.
    """
    flipped = bool(rng.random() < probability)
    if not flipped:
        return points, boxes, False
    points = points.copy()
    boxes = boxes.copy()
    points[:, 1] = -points[:, 1]
    boxes[:, 1] = -boxes[:, 1]
    boxes[:, 6] = wrap_angle(-boxes[:, 6])
    return points, boxes, True


def global_rotation(points: np.ndarray, boxes: np.ndarray, angle: float) -> tuple[np.ndarray, np.ndarray]:
    """Rotate the scene by ``angle`` radians CCW about the sensor's +z axis (points, box centres and headings)."""
    c, s = math.cos(angle), math.sin(angle)
    points = points.copy()
    boxes = boxes.copy()
    x, y = points[:, 0].astype(np.float64), points[:, 1].astype(np.float64)
    points[:, 0] = c * x - s * y
    points[:, 1] = s * x + c * y
    bx, by = boxes[:, 0].copy(), boxes[:, 1].copy()
    boxes[:, 0] = c * bx - s * by
    boxes[:, 1] = s * bx + c * by
    boxes[:, 6] = wrap_angle(boxes[:, 6] + angle)
    return points, boxes


def global_scaling(points: np.ndarray, boxes: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Scale the scene uniformly about the sensor origin: point ``xyz``, box centres and box sizes times ``scale``."""
    if not scale > 0:
        raise ValueError(f"scale must be > 0, got {scale}")
    points = points.copy()
    boxes = boxes.copy()
    points[:, :3] *= scale
    boxes[:, :6] *= scale
    return points, boxes


def filter_points_in_range(points: np.ndarray, point_cloud_range: tuple[float, ...]) -> np.ndarray:
    """Keep points with ``min <= p < max`` on x, y and z (the pillar indexing rule); NaN coordinates are dropped.

    ``point_cloud_range`` is ``[x_min, y_min, z_min, x_max, y_max, z_max]`` in metres (sensor frame).
    """
    lo = np.asarray(point_cloud_range[:3], dtype=np.float32)
    hi = np.asarray(point_cloud_range[3:], dtype=np.float32)
    xyz = points[:, :3]
    keep = np.all((xyz >= lo) & (xyz < hi), axis=1)
    return points[keep]


def filter_boxes_in_range(boxes: np.ndarray, point_cloud_range: tuple[float, ...]) -> np.ndarray:
    """(M,) bool: boxes whose BEV centre lies in the range's x-y rectangle (``min <= c <= max``, OpenPCDet's rule).

    Used to drop targets that augmentation or GT sampling pushed out of the detection range.
    """
    x0, y0, _, x1, y1, _ = point_cloud_range
    return (boxes[:, 0] >= x0) & (boxes[:, 0] <= x1) & (boxes[:, 1] >= y0) & (boxes[:, 1] <= y1)


def shuffle_points(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The points in a random order (which points survive the voxelizer's per-pillar cap depends on the order)."""
    return points[rng.permutation(len(points))]
