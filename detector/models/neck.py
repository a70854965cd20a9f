"""SECOND FPN neck: bring every backbone level to the block-1 resolution and concatenate (the paper's Fig. 5a).

Level i: ConvTranspose2d(C_i → 128, kernel = stride = u_i, no bias) → BN(eps 1e-3, mom 0.01) → ReLU with u = 1/2/4
(a 1x1 transposed conv for u = 1, as the reference), then concat → 384 channels at (ny/2, nx/2). Transposed convs
keep PyTorch's default init, as the reference. :func:`upsample_block` is public for the sparse ablations.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from detector.models.grad_layout import ConvTranspose2dStandardGrad
from detector.models.pillar_net import BN_EPS, BN_MOMENTUM


def upsample_block(in_channels: int, out_channels: int, stride: int) -> nn.Sequential:
    """ConvTranspose2d(kernel = stride, no bias) → BN → ReLU: (B, C_in, H, W) → (B, C_out, H*stride, W*stride)."""
    return nn.Sequential(
        ConvTranspose2dStandardGrad(in_channels, out_channels, stride, stride=stride, bias=False),
        nn.BatchNorm2d(out_channels, eps=BN_EPS, momentum=BN_MOMENTUM),
        nn.ReLU(inplace=True),
    )


class SecondFPN(nn.Module):
    """List of backbone maps → one map with ``sum(out_channels)`` channels at the finest level's resolution."""

    def __init__(
        self, *, in_channels: Sequence[int], out_channels: Sequence[int], upsample_strides: Sequence[int]
    ) -> None:
        super().__init__()
        if not (len(in_channels) == len(out_channels) == len(upsample_strides)):
            raise ValueError("SecondFPN: in_channels, out_channels and upsample_strides must have equal lengths")
        self.deblocks = nn.ModuleList(
            upsample_block(i, o, s) for i, o, s in zip(in_channels, out_channels, upsample_strides)
        )
        self.out_channels = int(sum(out_channels))

    def forward(self, feats: Sequence[torch.Tensor]) -> torch.Tensor:
        """[(B, C_i, H_i, W_i)] → (B, sum(out_channels), H_0 * u_0, W_0 * u_0) (e.g. 384 at ny/2, nx/2)."""
        if len(feats) != len(self.deblocks):
            raise ValueError(f"SecondFPN: expected {len(self.deblocks)} maps, got {len(feats)}")
        return torch.cat([d(f) for d, f in zip(self.deblocks, feats)], dim=1)
