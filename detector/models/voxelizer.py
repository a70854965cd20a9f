"""Points → pillars: crop, index, cap, pad (the first half of the paper's "Feature Extract" timer).

The pillar index of a point comes from :func:`mpchair.geometry.pillar_coords` (the one indexing rule of the project:
keep ``min <= p < max`` on x, y, z; cell ``floor((p - min) / voxel)``). That function works on numpy arrays, so the
xyz columns are copied to the host once per sample; everything after it is vectorised torch on the points' device.

Caps (reference: 32 points per pillar, 16,000 pillars in training, 40,000 in testing). The reference op does not say
which points/pillars survive a cap, so the rule here is fixed and documented: **pillars are numbered in order of
their first point in the input order** and the first ``max_pillars`` are kept; **within a pillar, the first
``max_points`` points in input order** are kept. Both fall out of one stable sort by pillar key (no Python loop over
points). Pillars whose cell lies outside the padded canvas ``output_shape`` are dropped (the reference's upstream
fix); with a canvas at least as large as the real grid none are.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch

from mpchair.geometry import pillar_coords


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


def _sample_pillars(
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
    Returns :class:`Voxels` with pillars ordered by sample, then by first occurrence.
    """
    if len(points_list) == 0:
        raise ValueError("voxelize: empty batch")
    parts_p, parts_n, parts_c = [], [], []
    for b, pts in enumerate(points_list):
        if pts.dim() != 2 or pts.shape[1] < 3:
            raise ValueError(f"voxelize: sample {b} has shape {tuple(pts.shape)}, expected (N, C>=3)")
        p, n, c = _sample_pillars(pts, point_cloud_range, voxel_size, output_shape, max_points, max_pillars)
        bcol = torch.full((c.shape[0], 1), b, dtype=torch.int64, device=c.device)
        parts_p.append(p)
        parts_n.append(n)
        parts_c.append(torch.cat([bcol, c], dim=1))
    return Voxels(torch.cat(parts_p), torch.cat(parts_n), torch.cat(parts_c), len(points_list))
