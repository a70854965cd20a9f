"""Synthetic active-site patterns for tests and benchmarks of the sparse ops.

``clustered_sites`` imitates a BEV pillar occupancy of an indoor or street scan: filled blobs (furniture, cars) and
thin wall segments with gaps, so that most active sites have several active 8-neighbours (about 4 on average, like
real scans). ``uniform_sites`` draws sites independently (about 0 - 1 active neighbours at low density), the
worst case for sparse convolution. Coordinates are grid indices ``[batch, iy, ix]`` (see ``detector.sparse.tensor``).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor


def _clustered_mask(shape: tuple[int, int], count: int, gen: torch.Generator) -> Tensor:
    h, w = shape
    mask = torch.zeros(h, w, dtype=torch.bool)

    def rand() -> float:
        return float(torch.rand((), generator=gen))

    active = 0  # tracked per shape: a full-canvas sum every iteration would dominate the generator's time
    while active < count:
        if rand() < 0.5:
            # blob: a disc of radius 1.5 - 6 cells, 80 % of its cells occupied
            cy, cx, r = rand() * h, rand() * w, 1.5 + 4.5 * rand()
            y0, y1 = max(0, int(cy - r)), min(h, int(cy + r) + 1)
            x0, x1 = max(0, int(cx - r)), min(w, int(cx + r) + 1)
            if y0 >= y1 or x0 >= x1:
                continue
            yy, xx = torch.meshgrid(torch.arange(y0, y1), torch.arange(x0, x1), indexing="ij")
            inside = (yy - cy) ** 2 + (xx - cx) ** 2 <= r * r
            keep = torch.rand(inside.shape, generator=gen) < 0.8
            patch = mask[y0:y1, x0:x1]
            before = int(patch.sum())
            patch |= inside & keep
            active += int(patch.sum()) - before
        else:
            # wall: a segment 8 - 80 cells long, 1 - 2 cells thick, 90 % of its cells occupied
            y0, x0, theta = rand() * h, rand() * w, rand() * math.pi
            length, thick = 8 + 72 * rand(), 1 + int(rand() < 0.5)
            t = torch.arange(int(length), dtype=torch.float64)
            for k in range(thick):
                ys = (y0 + t * math.sin(theta) + k * math.cos(theta)).round().long()
                xs = (x0 + t * math.cos(theta) - k * math.sin(theta)).round().long()
                ok = (ys >= 0) & (ys < h) & (xs >= 0) & (xs < w) & (torch.rand(t.shape, generator=gen) < 0.9)
                ys, xs = ys[ok], xs[ok]
                new = torch.unique(ys * w + xs)
                active += int((~mask.view(-1)[new]).sum())
                mask[ys, xs] = True
    return mask


def _sites(
    spatial_shape: tuple[int, int],
    density: float,
    batch_size: int,
    seed: int,
    device: str | torch.device,
    item_yx: Callable[[int, torch.Generator], Tensor],
) -> Tensor:
    """``(N, 3)`` ``[b, iy, ix]`` from ``item_yx(count, generator)`` → sorted ``(count, 2)`` ``[iy, ix]`` per item."""
    gen = torch.Generator().manual_seed(seed)
    count = max(1, round(density * spatial_shape[0] * spatial_shape[1]))
    out = []
    for b in range(batch_size):
        yx = item_yx(count, gen)
        out.append(torch.cat([torch.full((yx.shape[0], 1), b, dtype=torch.int64), yx], dim=1))
    return torch.cat(out).to(device)


def clustered_sites(
    spatial_shape: tuple[int, int],
    density: float,
    batch_size: int = 1,
    seed: int = 0,
    device: str | torch.device = "cpu",
) -> Tensor:
    """``(N, 3)`` int64 ``[b, iy, ix]`` sorted sites: blobs and wall segments, ``round(density * H * W)`` per item."""

    def item(count: int, gen: torch.Generator) -> Tensor:
        yx = _clustered_mask(spatial_shape, count, gen).nonzero()
        # trim the overshoot of the last shape at random so every item has exactly `count` sites
        return yx[torch.randperm(yx.shape[0], generator=gen)[:count].sort().values]

    return _sites(spatial_shape, density, batch_size, seed, device, item)


def uniform_sites(
    spatial_shape: tuple[int, int],
    density: float,
    batch_size: int = 1,
    seed: int = 0,
    device: str | torch.device = "cpu",
) -> Tensor:
    """``(N, 3)`` int64 ``[b, iy, ix]`` sorted sites, uniform without replacement, ``round(density * H * W)`` each."""
    w = spatial_shape[1]

    def item(count: int, gen: torch.Generator) -> Tensor:
        flat = torch.randperm(spatial_shape[0] * w, generator=gen)[:count].sort().values
        return torch.stack([flat // w, flat % w], dim=1)

    return _sites(spatial_shape, density, batch_size, seed, device, item)


def mean_active_neighbours(coords: Tensor, spatial_shape: tuple[int, int]) -> float:
    """Average number of active 8-neighbours per active site (a summary of how clustered a pattern is)."""
    from detector.sparse.indices import SiteLookup, flat_keys, subm_table

    if coords.shape[0] == 0:
        return 0.0
    batch = int(coords[:, 0].max()) + 1
    table = subm_table(coords, spatial_shape, SiteLookup(flat_keys(coords, spatial_shape), spatial_shape, batch), 3)
    return float((table.table >= 0).sum() - coords.shape[0]) / coords.shape[0]
