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
from detector.ops.gemm import linear, uses_onednn
from detector.sparse.norm import batch_norm_into
from detector.sparse.workspace import Workspace

#: oneDNN allocates its GEMM outputs, so the neck computes a level in chunks of coarse rows whose product stays below
#: this size: held in the heap (glibc serves blocks above its mmap threshold, at most 32 MiB, with fresh mmaps, i.e.
#: page faults every frame) and still in cache when copied into the map.
CHUNK_BYTES = 4 << 20


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

    def forward(self, feats: Sequence[torch.Tensor], workspace: Workspace | None = None) -> torch.Tensor:
        """[(B, C_i, H_i, W_i)] → (B, sum(out_channels), H_0 * u_0, W_0 * u_0) (e.g. 384 at ny/2, nx/2).

        ``workspace`` (inference, eval mode): every level is computed straight into its channel slice of one reused
        channels-last map (:meth:`_into_map`), valid until the next call."""
        if len(feats) != len(self.deblocks):
            raise ValueError(f"SecondFPN: expected {len(self.deblocks)} maps, got {len(feats)}")
        if workspace is not None and not self.training:
            return self._into_map(feats, workspace)
        return torch.cat([d(f) for d, f in zip(self.deblocks, feats)], dim=1)

    def _into_map(self, feats: Sequence[torch.Tensor], workspace: Workspace) -> torch.Tensor:
        """The levels as GEMMs into one (B, H, W, sum(O)) buffer, returned as its (B, sum(O), H, W) view.

        A level with kernel = stride = u is, per coarse pixel, one ``(C_in) x (C_in, u*u*O)`` product whose u x u x O
        values are the u x u fine pixels' outputs: one matmul over all coarse pixels, its rows copied into the
        level's channel slice of the map with the fine pixels interleaved, then BatchNorm (batch_norm's own kernel)
        and ReLU in place there. Nothing is allocated per frame (the 50 MB level maps, their BatchNorm outputs and
        the 151 MB concatenation were fresh mmaps, i.e. page faults, every frame) and the concatenation copy is
        gone; the values are the ``ConvTranspose2d`` + ``BatchNorm2d`` + ``ReLU`` ones up to float rounding (the
        matmul sums in another order than oneDNN's deconvolution).
        """
        b, _, h0, w0 = feats[0].shape
        u0 = self.deblocks[0][0].stride[0]
        hh, ww = h0 * u0, w0 * u0
        x0 = feats[0]
        out = workspace.take(self, "map", (b, hh, ww, self.out_channels), x0.dtype, x0.device)
        col = 0
        for i, (deblock, f) in enumerate(zip(self.deblocks, feats)):
            deconv, norm = deblock[0], deblock[1]
            cin, o, u = deconv.in_channels, deconv.out_channels, deconv.stride[0]
            _, _, h, w = f.shape
            rows = f.permute(0, 2, 3, 1).reshape(b * h * w, cin).to(x0.dtype)  # a view for a channels-last map
            # column (ky * u + kx) * O + o; in the map's dtype (out= is not autocast: bf16 inference casts by hand)
            wmat = deconv.weight.permute(0, 2, 3, 1).reshape(cin, u * u * o).to(x0.dtype)
            dst = out[..., col : col + o]  # (B, H, W, O) slice of the map
            if uses_onednn(rows, wmat):
                # oneDNN's GEMM (detector.ops.gemm) a chunk of coarse rows at a time, each chunk's (rows, u*u*O)
                # product copied into its u fine rows of the slice
                fine = dst.view(b * h, u, w, u, o)
                step = max(1, CHUNK_BYTES // (w * u * u * o * rows.element_size()))
                for r0 in range(0, b * h, step):
                    r1 = min(b * h, r0 + step)
                    y = linear(rows[r0 * w : r1 * w], wmat.t())
                    fine[r0:r1].copy_(y.view(r1 - r0, w, u, u, o).permute(0, 2, 1, 3, 4))
            elif u == 1:
                torch.mm(rows, wmat, out=dst.view(b * h * w, o))
            else:
                prod = workspace.take(self, f"level{i}", (b * h * w, u * u * o), f.dtype, f.device)
                torch.mm(rows, wmat, out=prod)
                # (b, h, w, ky, kx, o) → fine pixel (h * u + ky, w * u + kx)
                dst.view(b, h, u, w, u, o).copy_(prod.view(b, h, w, u, u, o).permute(0, 1, 3, 2, 4, 5))
            if deconv.bias is not None:
                dst.add_(deconv.bias)
            nchw = dst.permute(0, 3, 1, 2)
            batch_norm_into(norm, nchw, nchw)
            dst.clamp_min_(0)
            col += o
        return out.permute(0, 3, 1, 2)
