"""KITTI ``velodyne/%06d.bin``: raw little-endian float32 rows ``x, y, z, reflectance`` in the LiDAR/sensor frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mpchair.atomic import atomic_open
from mpchair.errors import InputError

_ROW_BYTES = 16  # 4 x float32


def read_velodyne(path: str | Path) -> np.ndarray:
    """Read a scan as a (N,4) float32 array ``x, y, z, reflectance`` (sensor frame, metres).

    A file whose size is not a multiple of 16 bytes is an :class:`InputError`.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError("velodyne file not found", path) from None
    except OSError as e:
        raise InputError(f"cannot read velodyne file: {e}", path) from None
    if len(data) % _ROW_BYTES:
        raise InputError(f"size {len(data)} bytes is not a multiple of {_ROW_BYTES} (float32 x, y, z, r rows)", path)
    return np.frombuffer(data, dtype="<f4").astype(np.float32).reshape(-1, 4)


def write_velodyne(path: str | Path, points: np.ndarray) -> None:
    """Atomically write (N,4) points (sensor frame, metres; cast to little-endian float32) as a KITTI ``.bin``."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 4:
        raise ValueError(f"write_velodyne expects (N, 4) points, got shape {points.shape}")
    with atomic_open(path, "wb") as f:
        f.write(np.ascontiguousarray(points, dtype="<f4").tobytes())
