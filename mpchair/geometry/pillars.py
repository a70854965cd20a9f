"""The one pillar indexing rule and the pseudoimage grid, shared by the detector's voxelizer and ``mpchair stats``.

``pc_range = (x_min, y_min, z_min, x_max, y_max, z_max)`` (sensor frame, metres); a point is kept iff
``min <= p < max`` on x, y and z (half-open), and its pillar is ``(iy, ix) = floor((p - min) / voxel)`` on y and x.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from mpchair.core.config import at_key_line, from_dict, load_derived_yaml
from mpchair.core.errors import InputError


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


# ------------------------------------------------------------------------------------------- the pseudoimage grid


@dataclass(frozen=True)
class PseudoimageGeometry:
    """The pillar grid of a model: where points are kept and how large the pseudoimage canvas is.

    ``point_cloud_range`` ``(x_min, y_min, z_min, x_max, y_max, z_max)`` sensor frame, metres; ``voxel_size``
    ``(vx, vy)`` metres; ``grid`` ``(W, H)`` = ``(nx, ny)`` cells of the (possibly padded) canvas. The one definition
    of the canvas that the detector's density figures and ``mpchair stats --density`` share.
    """

    point_cloud_range: tuple[float, float, float, float, float, float]
    voxel_size: tuple[float, float]
    grid: tuple[int, int]

    def __post_init__(self) -> None:
        try:
            nx, ny = grid_size(self.point_cloud_range, self.voxel_size)
        except ValueError as e:
            raise InputError(str(e)) from None
        W, H = self.grid
        if W < nx or H < ny:
            raise InputError(
                f"grid {W} x {H} is smaller than the range's {nx} x {ny} pillars (range {list(self.point_cloud_range)}"
                f", voxel {list(self.voxel_size)})")

    @property
    def real_grid(self) -> tuple[int, int]:
        """``(nx, ny)``: pillars the range itself spans (``<= grid``)."""
        return grid_size(self.point_cloud_range, self.voxel_size)

    def to_dict(self) -> dict:
        """JSON-able form (``grid`` and ``real_grid`` as ``[W, H]``)."""
        return {
            "point_cloud_range": list(self.point_cloud_range),
            "voxel_size": list(self.voxel_size),
            "grid": list(self.grid),
            "real_grid": list(self.real_grid),
        }


#: Matterport-Chair model geometry (paper V-A): 5 cm pillars, range [0, 25] x [-19, 19] x [-2, 2] m, canvas 512 x 768.
MATTERPORT_GEOMETRY = PseudoimageGeometry((0.0, -19.0, -2.0, 25.0, 19.0, 2.0), (0.05, 0.05), (512, 768))
#: KITTI car geometry (paper V-B): 16 cm pillars, range [0, 69.12] x [-39.68, 39.68] x [-3, 1] m, padded canvas
#: 440 x 504 (the paper's "504 x 440 pillar pseudoimage"; real grid 432 x 496).
KITTI_GEOMETRY = PseudoimageGeometry((0.0, -39.68, -3.0, 69.12, 39.68, 1.0), (0.16, 0.16), (440, 504))
PRESETS: dict[str, PseudoimageGeometry] = {"matterport": MATTERPORT_GEOMETRY, "kitti": KITTI_GEOMETRY}


@dataclass(frozen=True)
class _GridKeys:
    """The three grid keys of a model YAML's ``model`` section (the detector's schema owns the rest)."""

    point_cloud_range: tuple[float, float, float, float, float, float]
    voxel_size: tuple[float, ...]
    output_shape: tuple[int, int]


def geometry_from_model_yaml(path: str | Path) -> PseudoimageGeometry:
    """The pseudoimage geometry of a detector model YAML: ``model.point_cloud_range``, ``model.voxel_size`` (first
    two used) and ``model.output_shape`` (``[ny, nx]``). Only these keys are read (``detector`` validates the rest
    when it loads the file); a missing or mistyped one, or a canvas smaller than the range's grid, is an
    :class:`InputError` naming the file and the key. A file that derives from another (``_BASE_CONFIG_``) reads its
    base's keys, which must be a YAML path relative to the file (the detector's packaged configs name theirs so)."""
    data = load_derived_yaml(path)
    try:
        return _grid_of(data, path)
    except InputError as e:  # with the line of the key at fault
        raise at_key_line(e, path) from None


def _grid_of(data: dict, path: str | Path) -> PseudoimageGeometry:
    """:func:`geometry_from_model_yaml` of the loaded mapping ``data`` (errors name ``path``, no line yet)."""
    model = data.get("model")
    if not isinstance(model, dict):
        raise InputError("model: expected a mapping with point_cloud_range, voxel_size and output_shape", path)
    keys = [f.name for f in fields(_GridKeys)]
    missing = [k for k in keys if k not in model]
    if missing:
        raise InputError(f"model.{missing[0]}: missing (the pillar grid needs {', '.join(keys)})", path)
    grid = from_dict(_GridKeys, {k: model[k] for k in keys}, source=str(path), prefix="model.")
    ny, nx = grid.output_shape
    try:
        return PseudoimageGeometry(grid.point_cloud_range, tuple(grid.voxel_size[:2]), (nx, ny))
    except InputError as e:
        raise InputError(f"model.point_cloud_range / voxel_size / output_shape: {e.message}", path) from None


def frame_density(points: np.ndarray, geometry: PseudoimageGeometry) -> tuple[int, int, float]:
    """``(points_in_range, non_empty_pillars, D)`` of one (N, >=3) sensor-frame scan.

    ``D = non_empty_pillars / (W * H)`` with ``W x H`` = ``geometry.grid`` (the padded canvas the backbone convolves);
    pillars from :func:`pillar_coords` (the detector's voxelization rule).
    """
    coords, keep = pillar_coords(points, geometry.point_cloud_range, geometry.voxel_size)
    W, H = geometry.grid
    pillars = int(np.unique(coords[:, 0] * W + coords[:, 1]).size)
    return int(keep.sum()), pillars, pillars / float(W * H)
