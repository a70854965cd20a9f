"""KITTI-odometry sequence files: ``times.txt`` (capture time per frame, seconds) and ``poses.txt`` (one 3x4 pose per
frame, row-major: 12 numbers per line).

Times are held as int64 **microseconds** and written with exactly 6 decimals, so they survive the text round trip
unchanged (KITTI's own ``%e`` times are read too, rounded to the microsecond) and ``emitted <= captured``
comparisons on them are exact. Poses are (4,4) float64 transforms; mpchair writes sensor → world
(``T_world_from_sensor``).
"""

from __future__ import annotations

from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from mpchair.core.atomic import write_text
from mpchair.core.errors import InputError
from mpchair.core.text import read_text

#: Largest capture time read (seconds; ~31,700 years, far above any clock, well inside int64 microseconds).
MAX_SECONDS = Decimal("1e12")
#: How far a pose's rotation may be from orthonormal (``%.9e`` text keeps real ones within 1e-8).
RIGID_TOL = 1e-4


def format_times(times_us: np.ndarray) -> str:
    """``times.txt`` text: one line per frame, seconds with exactly 6 decimals, from integer microseconds (>= 0)."""
    return "".join(f"{int(t) // 1_000_000}.{int(t) % 1_000_000:06d}\n" for t in times_us)


def read_times(path: str | Path) -> np.ndarray:
    """(N,) int64 microseconds of a ``times.txt`` (one non-negative time in seconds per line: ``12.345678`` as mpchair
    writes it, or KITTI's ``1.234568e+01``; read exactly as decimals and rounded to the microsecond), strictly
    increasing; anything else is an :class:`InputError` naming the line."""
    path = Path(path)
    out = []
    for n, line in enumerate(read_text(path, "times file").splitlines(), 1):
        try:
            seconds = Decimal(line.strip())
        except InvalidOperation:
            seconds = Decimal("NaN")
        if not seconds.is_finite() or not 0 <= seconds <= MAX_SECONDS:
            raise InputError(f"expected a time in seconds (0 to {MAX_SECONDS:.0e}), got {line.strip()[:40]!r}", path,
                             n)
        out.append(int((seconds * 1_000_000).to_integral_value(ROUND_HALF_EVEN)))
    t = np.array(out, dtype=np.int64)
    if len(t) == 0:
        raise InputError("no capture times", path)
    bad = np.flatnonzero(np.diff(t) <= 0)
    if len(bad):
        raise InputError("capture times must increase (after rounding to the microsecond)", path, int(bad[0]) + 2)
    return t


def format_poses(poses: np.ndarray) -> str:
    """``poses.txt`` text: the top 3x4 of each (4,4) pose, row-major, 12 numbers per line (``%.9e``)."""
    return "".join(" ".join(f"{v:.9e}" for v in T[:3].reshape(-1)) + "\n" for T in np.asarray(poses))


def read_poses(path: str | Path) -> np.ndarray:
    """(N,4,4) float64 rigid poses of a ``poses.txt``; a line without 12 finite numbers, or whose 3x3 block is not a
    rotation (orthonormal within :data:`RIGID_TOL`, determinant +1), is an :class:`InputError` naming the line."""
    path = Path(path)
    rows = []
    for n, line in enumerate(read_text(path, "poses file").splitlines(), 1):
        try:
            v = [float(x) for x in line.split()]
        except ValueError:
            v = []
        if len(v) != 12 or not np.all(np.isfinite(v)):
            raise InputError("expected 12 finite numbers (a 3x4 pose, row-major)", path, n)
        T = np.eye(4)
        T[:3] = np.array(v).reshape(3, 4)
        R = T[:3, :3]
        if np.abs(R.T @ R - np.eye(3)).max() > RIGID_TOL or np.linalg.det(R) < 0:
            raise InputError("not a rigid pose: the 3x3 block is not a rotation (scale, shear or reflection)", path, n)
        rows.append(T)
    return np.array(rows).reshape(-1, 4, 4)


def write_times(path: str | Path, times_us: np.ndarray) -> None:
    """Atomically write a ``times.txt``."""
    write_text(path, format_times(times_us))


def write_poses(path: str | Path, poses: np.ndarray) -> None:
    """Atomically write a ``poses.txt``."""
    write_text(path, format_poses(poses))
