"""KITTI ``velodyne/%06d.bin``: raw little-endian float32 rows ``x, y, z, reflectance`` in the LiDAR/sensor frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mpchair.core.atomic import atomic_open
from mpchair.core.errors import InputError

_ROW_BYTES = 16  # 4 x float32


def read_velodyne(path: str | Path) -> np.ndarray:
    """Read a scan as a (N,4) float32 array ``x, y, z, reflectance`` (sensor frame, metres).

    A file whose size is not a multiple of 16 bytes, or that holds a NaN or infinite value, is an :class:`InputError`
    naming it (every command reads scans here: ``view``, ``stats``, ``train``, ``eval``, ``stream-eval``).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError("velodyne file not found", path) from None
    except OSError as e:
        raise InputError(f"cannot read velodyne file: {e}", path) from None
    _check_size(path, len(data))
    points = np.frombuffer(data, dtype="<f4").astype(np.float32).reshape(-1, 4)
    finite = np.isfinite(points)
    if not finite.all():
        # a NaN would pass every range filter (each comparison is False) and poison the pillars, the boxes and the
        # pictures further on, where nothing names the file
        row, col = np.argwhere(~finite)[0]
        what = ("x", "y", "z", "reflectance")[col]
        raise InputError(f"point {row} has a non-finite {what} ({points[row, col]}); a scan holds finite x, y, z, "
                         "reflectance", path)
    return points


def velodyne_rows(path: str | Path) -> int:
    """Number of points in a scan file, from its size alone (the errors of :func:`read_velodyne`, nothing read)."""
    path = Path(path)
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise InputError("velodyne file not found", path) from None
    except OSError as e:
        raise InputError(f"cannot read velodyne file: {e}", path) from None
    _check_size(path, size)
    return size // _ROW_BYTES


def _check_size(path: Path, size: int) -> None:
    if size % _ROW_BYTES:
        raise InputError(f"size {size} bytes is not a multiple of {_ROW_BYTES} (float32 x, y, z, r rows)", path)


def write_velodyne(path: str | Path, points: np.ndarray) -> None:
    """Atomically write (N,4) points (sensor frame, metres; cast to little-endian float32) as a KITTI ``.bin``."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 4:
        raise ValueError(f"write_velodyne expects (N, 4) points, got shape {points.shape}")
    with atomic_open(path, "wb") as f:
        f.write(np.ascontiguousarray(points, dtype="<f4").tobytes())
