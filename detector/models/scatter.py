"""Dense scatter: pillar features → pseudo-image (the paper's "Feature Net" timer for the dense model).

Pillar ``(b, iy, ix)`` lands at flat index ``iy * nx + ix`` of sample ``b``'s zero canvas; cells without a pillar stay
exactly zero (that is what makes the sparse head exact downstream).
"""

from __future__ import annotations

import torch
from torch import nn


def scatter_to_canvas(
    features: torch.Tensor,
    coords: torch.Tensor,
    batch_size: int,
    output_shape: tuple[int, int],
    channels_last: bool = False,
) -> torch.Tensor:
    """features (P, C), coords (P, 3) int64 [b, iy, ix] → canvas (B, C, ny, nx), zero where no pillar.

    Coordinates must be unique and inside the canvas (the voxelizer guarantees both). ``channels_last=True`` returns
    the same values with ``torch.channels_last`` strides (the scatter's own (B, ny, nx, C) buffer, no copy).
    """
    ny, nx = output_shape
    c = features.shape[1]
    flat = (coords[:, 0] * ny + coords[:, 1]) * nx + coords[:, 2]
    canvas = features.new_zeros((batch_size * ny * nx, c))
    canvas = canvas.index_copy(0, flat, features)
    canvas = canvas.view(batch_size, ny, nx, c).permute(0, 3, 1, 2)
    return canvas if channels_last else canvas.contiguous()


class PointPillarsScatter(nn.Module):
    """Module wrapper of :func:`scatter_to_canvas` for a fixed ``output_shape`` [ny, nx] (cells)."""

    def __init__(self, *, output_shape: tuple[int, int]) -> None:
        super().__init__()
        self.output_shape = (int(output_shape[0]), int(output_shape[1]))

    def forward(self, features: torch.Tensor, coords: torch.Tensor, batch_size: int) -> torch.Tensor:
        """(P, C), (P, 3) [b, iy, ix] → (B, C, ny, nx)."""
        return scatter_to_canvas(features, coords, batch_size, self.output_shape)
