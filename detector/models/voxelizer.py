"""Points → pillars: crop, index, cap, pad (the first half of the paper's "Feature Extract" timer).

The pillar index of a point is the project's one indexing rule, :func:`mpchair.geometry.pillar_coords`: keep
``min <= p < max`` on x, y, z (float64); cell ``floor((p - min) / voxel)`` on y and x, held at ``n - 1`` of the real
grid. Pillars whose cell lies outside the padded canvas ``output_shape`` are dropped (the reference's upstream fix);
with a canvas at least as large as the real grid none are.

Caps (reference: 32 points per pillar, 16,000 pillars in training, 40,000 in testing). The reference op does not say
which points/pillars survive a cap, so the rule here is fixed and documented: **pillars are numbered in order of
their first point in the input order** and the first ``max_pillars`` are kept; **within a pillar, the first
``max_points`` points in input order** are kept.

Two implementations of that one rule, equal bit for bit (tested):

* :func:`voxelize` (used by the models): one compiled pass over the points in input order (``_pillars_of_sample``,
  numba) with a canvas-sized table ``cell → pillar``: a point opens a pillar on its cell's first arrival (while fewer
  than ``max_pillars`` are open) and takes the next slot while fewer than ``max_points`` are taken, which *is* the
  rule; a second pass copies the kept points into the padded ``(P, T, C)`` block. It computes the cell with the same
  float64 operations as ``pillar_coords``. On a GPU the points go to the host and the pillars come back (the indexing
  rule is host code in either form); float32 and float64 points only (others take the torch form).
* :func:`voxelize_torch` (the form before it: ``pillar_coords`` on the host, then one stable sort by pillar key in
  vectorised torch on the points' device), kept as the reference the kernel is tested and benchmarked against
  (``tools/bench_feature_extract.py``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch

from mpchair.core.jit import njit_cached
from mpchair.geometry import grid_size, pillar_coords


class Voxels(NamedTuple):
    """A batch of pillars.

    pillars: (P, T, C) float, the raw point features (x, y, z[, r]; sensor frame, metres) of each pillar, zero-padded
        after the first ``num_points[p]`` slots. T = max points per pillar.
    num_points: (P,) int64, real points per pillar (1..T).
    coords: (P, 3) int64 ``[b, iy, ix]``: sample index in the batch, pillar row (y) and column (x).
    batch_size: number of samples B (samples may contribute no pillar at all).
    """

    pillars: torch.Tensor
    num_points: torch.Tensor
    coords: torch.Tensor
    batch_size: int


@njit_cached
def _pillars_of_sample(
    points: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    voxel: np.ndarray,
    grid_ny: int,
    grid_nx: int,
    canvas_ny: int,
    canvas_nx: int,
    max_points: int,
    max_pillars: int,
    sample: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """points (N, C) (sensor frame, m) → pillars (P, T, C) zero-padded, num_points (P,), coords (P, 3) [b, iy, ix]."""
    n = points.shape[0]
    c = points.shape[1]
    # table[cell] = pillar index + 1 (0: no pillar yet); slot[i] = pillar * T + rank of point i, or -1 if dropped
    table = np.zeros(canvas_ny * canvas_nx, dtype=np.int32)
    slot = np.empty(n, dtype=np.int64)
    counts = np.zeros(min(n, max_pillars), dtype=np.int64)
    cells = np.empty(min(n, max_pillars), dtype=np.int64)
    n_pillars = 0
    for i in range(n):
        slot[i] = -1
        # pillar_coords' rule, with its float64 operations: keep min <= p < max, floor((p - min) / v), held at n - 1
        x = np.float64(points[i, 0])
        y = np.float64(points[i, 1])
        z = np.float64(points[i, 2])
        if not (x >= lo[0] and x < hi[0] and y >= lo[1] and y < hi[1] and z >= lo[2] and z < hi[2]):
            continue
        ix = min(np.int64(np.floor((x - lo[0]) / voxel[0])), grid_nx - 1)
        iy = min(np.int64(np.floor((y - lo[1]) / voxel[1])), grid_ny - 1)
        if iy >= canvas_ny or ix >= canvas_nx:
            continue
        cell = iy * canvas_nx + ix
        pid = table[cell] - 1
        if pid < 0:
            if n_pillars == max_pillars:
                continue
            pid = n_pillars
            table[cell] = pid + 1
            cells[pid] = cell
            n_pillars += 1
        rank = counts[pid]
        if rank < max_points:
            slot[i] = pid * max_points + rank
            counts[pid] = rank + 1
    pillars = np.zeros((n_pillars, max_points, c), dtype=points.dtype)
    flat = pillars.reshape(n_pillars * max_points, c)
    for i in range(n):
        s = slot[i]
        if s >= 0:
            for k in range(c):
                flat[s, k] = points[i, k]
    coords = np.empty((n_pillars, 3), dtype=np.int64)
    for p in range(n_pillars):
        coords[p, 0] = sample
        coords[p, 1] = cells[p] // canvas_nx
        coords[p, 2] = cells[p] % canvas_nx
    return pillars, counts[:n_pillars].copy(), coords


def _check_batch(points_list: Sequence[torch.Tensor]) -> None:
    if len(points_list) == 0:
        raise ValueError("voxelize: empty batch")
    for b, pts in enumerate(points_list):
        if pts.dim() != 2 or pts.shape[1] < 3:
            raise ValueError(f"voxelize: sample {b} has shape {tuple(pts.shape)}, expected (N, C>=3)")


def voxelize(
    points_list: Sequence[torch.Tensor],
    *,
    point_cloud_range: tuple[float, float, float, float, float, float],
    voxel_size: tuple[float, float, float],
    output_shape: tuple[int, int],
    max_points: int,
    max_pillars: int,
) -> Voxels:
    """Group each sample's points into pillars and concatenate the batch.

    points_list: B tensors (N_i, C) float, columns x, y, z (sensor frame, metres) then optional extra features
        (e.g. reflectance). All on one device.
    point_cloud_range: [x_min, y_min, z_min, x_max, y_max, z_max] (m); voxel_size: [vx, vy, vz] (m).
    output_shape: [ny, nx] cells of the (padded) canvas; pillars outside it are dropped.
    max_points / max_pillars: caps per pillar / per sample (rule in the module docstring).
    Returns :class:`Voxels` with pillars ordered by sample, then by first occurrence (no autograd to the points).
    """
    _check_batch(points_list)
    if any(p.dtype not in (torch.float32, torch.float64) for p in points_list):  # the kernel is compiled for these
        return voxelize_torch(points_list, point_cloud_range=point_cloud_range, voxel_size=voxel_size,
                              output_shape=output_shape, max_points=max_points, max_pillars=max_pillars)
    grid_nx, grid_ny = grid_size(point_cloud_range, voxel_size)  # also validates range and voxel
    r = np.asarray(point_cloud_range, dtype=np.float64)
    voxel = np.asarray(voxel_size[:2], dtype=np.float64)
    canvas_ny, canvas_nx = int(output_shape[0]), int(output_shape[1])
    device = points_list[0].device
    parts = []
    for b, pts in enumerate(points_list):
        host = np.ascontiguousarray(pts.detach().cpu().numpy())
        parts.append(_pillars_of_sample(host, r[:3], r[3:], voxel, grid_ny, grid_nx, canvas_ny, canvas_nx,
                                        int(max_points), int(max_pillars), b))
    if len(parts) == 1:
        pillars, counts, coords = (torch.from_numpy(a) for a in parts[0])
    else:
        pillars, counts, coords = (torch.from_numpy(np.concatenate(a)) for a in zip(*parts))
    return Voxels(pillars.to(device), counts.to(device), coords.to(device), len(points_list))


# --------------------------------------------------------------------------- the vectorised-torch form (reference)


def _sample_pillars_torch(
    points: torch.Tensor,
    pc_range: tuple[float, ...],
    voxel_size: tuple[float, ...],
    output_shape: tuple[int, int],
    max_points: int,
    max_pillars: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One sample: points (N, C) → pillars (P, T, C), num_points (P,), coords (P, 2) [iy, ix]."""
    device, c = points.device, points.shape[1]
    ny, nx = output_shape
    xyz = points[:, :3].detach().cpu().numpy().astype(np.float64, copy=False)
    cells_np, keep_np = pillar_coords(xyz, pc_range, voxel_size)
    keep = torch.from_numpy(np.ascontiguousarray(keep_np)).to(device)
    cells = torch.from_numpy(np.ascontiguousarray(cells_np, dtype=np.int64)).to(device)
    pts = points[keep]
    inside = (cells[:, 0] >= 0) & (cells[:, 0] < ny) & (cells[:, 1] >= 0) & (cells[:, 1] < nx)
    pts, cells = pts[inside], cells[inside]
    n = pts.shape[0]
    if n == 0:
        return (
            points.new_zeros((0, max_points, c)),
            torch.zeros(0, dtype=torch.int64, device=device),
            torch.zeros((0, 2), dtype=torch.int64, device=device),
        )
    key = cells[:, 0] * nx + cells[:, 1]
    # Stable sort: points of one pillar become a contiguous run, still in input order.
    sorted_key, order = torch.sort(key, stable=True)
    is_start = torch.ones(n, dtype=torch.bool, device=device)
    is_start[1:] = sorted_key[1:] != sorted_key[:-1]
    run_id = torch.cumsum(is_start, 0) - 1  # run index of each sorted point
    run_start = torch.nonzero(is_start).squeeze(1)  # sorted position where each run begins
    rank = torch.arange(n, device=device) - run_start[run_id]  # position of the point within its pillar
    first_index = order[run_start]  # input index of each pillar's first point (stable sort → the minimum)
    # Number pillars by first occurrence: the rank of first_index among all pillars.
    pillar_order = torch.argsort(first_index)
    pillar_id_of_run = torch.empty_like(pillar_order)
    pillar_id_of_run[pillar_order] = torch.arange(pillar_order.numel(), device=device)
    pid = pillar_id_of_run[run_id]
    n_pillars = min(pillar_order.numel(), max_pillars)
    take = (pid < n_pillars) & (rank < max_points)
    pid, rank, src = pid[take], rank[take], order[take]
    pillars = points.new_zeros((n_pillars, max_points, c))
    pillars[pid, rank] = pts[src]
    counts = torch.bincount(pid, minlength=n_pillars)
    first_of_pillar = first_index[pillar_order[:n_pillars]]
    return pillars, counts, cells[first_of_pillar]


def voxelize_torch(
    points_list: Sequence[torch.Tensor],
    *,
    point_cloud_range: tuple[float, float, float, float, float, float],
    voxel_size: tuple[float, float, float],
    output_shape: tuple[int, int],
    max_points: int,
    max_pillars: int,
) -> Voxels:
    """:func:`voxelize` in vectorised torch on the points' device (the reference form; same arguments, same output
    bit for bit, autograd to the points' features)."""
    _check_batch(points_list)
    parts_p, parts_n, parts_c = [], [], []
    for b, pts in enumerate(points_list):
        p, n, c = _sample_pillars_torch(pts, point_cloud_range, voxel_size, output_shape, max_points, max_pillars)
        bcol = torch.full((c.shape[0], 1), b, dtype=torch.int64, device=c.device)
        parts_p.append(p)
        parts_n.append(n)
        parts_c.append(torch.cat([bcol, c], dim=1))
    return Voxels(torch.cat(parts_p), torch.cat(parts_n), torch.cat(parts_c), len(points_list))
