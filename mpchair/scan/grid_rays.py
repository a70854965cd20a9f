"""World-frame rays of selected camera-grid pixels, compiled: the hot loop of dense visibility.

Dense visibility casts ~100k grid pixels per frame. Listing them (``np.nonzero``), building their sensor-frame
directions (:func:`mpchair.scan.sensors.grid_directions`), rotating them into the world frame and converting them to
Embree's float32 took about as long as the raycast itself in numpy (five passes and four temporary arrays); this
kernel does it in one pass over the rows that have a selected pixel. The directions are the same float64 numbers as
``rotate_vectors(grid_directions(...), R)`` (same operations in the same order), rounded once to float32.
"""

from __future__ import annotations

import functools

import numpy as np

from mpchair.core.jit import njit_cached
from mpchair.scan.sensors import CameraConfig, grid_directions


@functools.lru_cache(maxsize=8)
def grid_axes(camera: CameraConfig) -> tuple[np.ndarray, np.ndarray]:
    """``(y (W,), z (H,))`` float64, read-only: the sensor-frame direction of grid pixel ``(r, c)`` is
    ``(1, y[c], z[r])``."""
    w, h = camera.width, camera.height
    y = grid_directions(camera, np.zeros(w), np.arange(w))[:, 1].copy()
    z = grid_directions(camera, np.arange(h), np.zeros(h))[:, 2].copy()
    y.flags.writeable = False
    z.flags.writeable = False
    return y, z


@njit_cached
def _fill_rays(mask, used_rows, y, z, R, pixels, out):  # pragma: no cover - compiled
    k = 0
    w = mask.shape[1]
    for r in used_rows:
        zr = z[r]
        for c in range(w):
            if mask[r, c]:
                yc = y[c]
                pixels[k] = r * w + c
                for i in range(3):  # v @ R.T with v = (1, y, z), summed in rotate_vectors' order
                    out[k, i] = R[i, 0] + yc * R[i, 1] + zr * R[i, 2]
                k += 1
    return k


def mask_rays(mask: np.ndarray, camera: CameraConfig, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels set in ``mask`` (H,W bool) and their rays rotated by the sensor → world rotation ``R``.

    Returns ``pixels`` (N,) int64, the row-major flat indices ``row * W + col`` in increasing order, and world-frame
    directions (N,3) float32 (unnormalised, x = 1 in the sensor frame, so the ray parameter of a hit is its planar
    depth, metres).
    """
    mask = np.ascontiguousarray(mask, dtype=bool)
    if mask.shape != (camera.height, camera.width):
        raise ValueError(f"mask {mask.shape} is not the camera grid {(camera.height, camera.width)}")
    n = int(np.count_nonzero(mask))
    pixels = np.empty(n, dtype=np.int64)
    out = np.empty((n, 3), dtype=np.float32)
    if n:
        y, z = grid_axes(camera)
        _fill_rays(mask, np.flatnonzero(mask.any(axis=1)), y, z, np.ascontiguousarray(R, dtype=np.float64),
                   pixels, out)
    return pixels, out
