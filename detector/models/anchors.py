"""Anchor boxes on the head's feature map (Open3D-ML ``Anchor3DRangeGenerator`` semantics).

Two placements (``ModelConfig.anchor_centres``):

* ``range`` (the default, the reference's): centres are ``linspace(min, max, n)`` per axis over the **anchor
  range**, endpoints included and with no half-cell offset, where n is the feature-map size (x: W = nx/2,
  y: H = ny/2). This reproduces the reference's drift from the padded map's cell centres (up to 0.55 m in x on the
  768 x 512 Matterport map, ±5 cm on the 288 x 144 CPU map). A network trained on one grid learns offsets for its
  own drift; it is harmless there, but the drift differs from grid to grid (at the same place, the 768 x 512
  anchors sit 9-39 cm from the 288 x 144 ones), so weights moved to another grid would put every box off by it.
* ``cells``: each head-map cell's centre, ``origin + (i + 1/2) * cell`` (OpenPCDet's ``align_center``; origin the
  point-cloud range's minimum, cell the voxel size times the head map's stride), the same on every grid.
  :func:`detector.checkpoint.load_model` uses it whenever weights move to another grid.
The anchor range's z is the box **bottom** (0 for the chair, -1.78 for the KITTI car); anchors are returned with the
geometric centre z = bottom + h/2, the convention of every box in this project (the reference adds h/2 the same way
before coding).

Memory order is (y, x, size, rotation): anchor index ``((iy * W + ix) * n_sizes + s) * n_rots + r``. The head's
(B, H, W, A*K) output flattens in the same order, so anchor a at cell (iy, ix) uses channels ``[a*K, (a+1)*K)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch


def generate_anchors(
    *,
    feature_size: tuple[int, int],
    anchor_range: Sequence[float],
    sizes: Sequence[Sequence[float]],
    rotations: Sequence[float],
    cells: tuple[float, float, float, float] | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """All anchors of one sample: (H * W * n_sizes * n_rots, 7) ``[x, y, z_centre, l, w, h, yaw]``.

    feature_size: (H, W) of the head map. anchor_range: [x_min, y_min, z_bottom, x_max, y_max, z_bottom] (m, sensor
    frame). sizes: [[l, w, h], ...] (m; l along the heading). rotations: yaw values (rad, CCW from +x).
    cells: None for ``range`` placement; ``(x_origin, y_origin, cell_x, cell_y)`` (m) for ``cells`` placement, where
    only the anchor range's z is used.
    """
    h, w = feature_size
    x0, y0, zb, x1, y1, _ = (float(v) for v in anchor_range)
    if cells is None:
        xs = torch.linspace(x0, x1, w, dtype=torch.float64)
        ys = torch.linspace(y0, y1, h, dtype=torch.float64)
    else:
        ox, oy, cx, cy = (float(v) for v in cells)
        xs = ox + (torch.arange(w, dtype=torch.float64) + 0.5) * cx
        ys = oy + (torch.arange(h, dtype=torch.float64) + 0.5) * cy
    size_t = torch.tensor([list(map(float, s)) for s in sizes], dtype=torch.float64)  # (S, 3)
    rot_t = torch.tensor([float(r) for r in rotations], dtype=torch.float64)  # (R,)
    n_s, n_r = size_t.shape[0], rot_t.shape[0]
    shape = (h, w, n_s, n_r)
    x = xs.view(1, w, 1, 1).expand(shape)
    y = ys.view(h, 1, 1, 1).expand(shape)
    dims = size_t.view(1, 1, n_s, 1, 3).expand(*shape, 3)
    z = zb + dims[..., 2] / 2  # bottom → centre
    yaw = rot_t.view(1, 1, 1, n_r).expand(shape)
    anchors = torch.stack([x, y, z, dims[..., 0], dims[..., 1], dims[..., 2], yaw], dim=-1)
    return anchors.reshape(-1, 7).to(device=device, dtype=dtype)
