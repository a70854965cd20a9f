"""The one pillar indexing rule, shared by the detector's voxelizer and ``mpchair stats --density``.

``pc_range = (x_min, y_min, z_min, x_max, y_max, z_max)`` (sensor frame, metres); a point is kept iff
``min <= p < max`` on x, y and z (half-open), and its pillar is ``(iy, ix) = floor((p - min) / voxel)`` on y and x.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def _range_and_voxel(pc_range: Sequence[float], voxel_size: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    r = np.asarray(pc_range, dtype=np.float64).reshape(-1)
    v = np.asarray(voxel_size, dtype=np.float64).reshape(-1)
    if r.shape != (6,):
        raise ValueError(f"pc_range must be (x_min, y_min, z_min, x_max, y_max, z_max), got {pc_range!r}")
    if v.shape not in ((2,), (3,)) or np.any(v[:2] <= 0):
        raise ValueError(f"voxel_size must be 2 or 3 positive numbers (x, y[, z]), got {voxel_size!r}")
    if np.any(r[3:] <= r[:3]):
        raise ValueError(f"pc_range must have min < max on every axis, got {pc_range!r}")
    return r, v


def grid_size(pc_range: Sequence[float], voxel_size: Sequence[float]) -> tuple[int, int]:
    """Pillar grid ``(nx, ny)`` = ``(x_max - x_min) / vx``, ``(y_max - y_min) / vy``; must be whole numbers."""
    r, v = _range_and_voxel(pc_range, voxel_size)
    extent = (r[3:5] - r[0:2]) / v[:2]
    n = np.round(extent)
    if np.any(np.abs(extent - n) > 1e-6) or np.any(n < 1):
        raise ValueError(f"pc_range {pc_range!r} is not a whole number of voxels {voxel_size!r} on x and y")
    return int(n[0]), int(n[1])


def pillar_coords(
    points: np.ndarray, pc_range: Sequence[float], voxel_size: Sequence[float]
) -> tuple[np.ndarray, np.ndarray]:
    """Pillar indices of sensor-frame points: ``(coords (M,2) int64 [iy, ix], keep (N,) bool)``.

    ``points`` is (N, >=3) (float32 or float64; computed in float64). ``keep`` marks points with
    ``min <= p < max`` on x, y **and** z; ``coords`` holds ``floor((p - min) / voxel)`` for the kept points, in point
    order, on y then x. The x-y range must be a whole number of voxels (see :func:`grid_size`); an index that
    rounding would push to ``n`` for a point just below ``max`` is held at ``n - 1``.
    """
    r, v = _range_and_voxel(pc_range, voxel_size)
    nx, ny = grid_size(r, v)
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] < 3:
        raise ValueError(f"pillar_coords expects (N, 3+) points, got shape {p.shape}")
    xyz = p[:, :3].astype(np.float64)
    keep = np.all((xyz >= r[:3]) & (xyz < r[3:]), axis=1)
    kept = xyz[keep]
    ix = np.floor((kept[:, 0] - r[0]) / v[0]).astype(np.int64)
    iy = np.floor((kept[:, 1] - r[1]) / v[1]).astype(np.int64)
    coords = np.stack([np.minimum(iy, ny - 1), np.minimum(ix, nx - 1)], axis=1)
    return coords, keep
