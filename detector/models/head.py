"""Anchor head: three 1x1 convs on the neck map (the paper's "Head" timer), and its exact sparse twin.

At inference the three convs run as one 1x1 conv of their stacked weights (:meth:`AnchorHead.fused`), the same code
for the dense and the sparse model, which both hand it a channels-last map (see ``detector.models.scatter``), and
write one channel-planar output (each map's channels in one block, which post-processing reads).

Per cell and anchor a (A = n_sizes * n_rots): class logits at channels ``[a*K, (a+1)*K)``, 7 box residuals at
``[a*7, (a+1)*7)`` and 2 direction logits at ``[a*2, (a+1)*2)``. Init (reference): cls weights N(0, 0.01) with bias
-log((1 - 0.01) / 0.01) = -4.595 (prior probability 0.01), reg weights N(0, 0.01) with bias 0, dir PyTorch default.

:class:`SparseExactHead` holds the same parameters (same ``state_dict``) but evaluates the fused 1x1 conv as one Linear
layer on the *active* sites only and fills every other site with the bias. On a map that is exactly zero at inactive
sites (the sparse backbone's todense output) this is the dense head's output: a 1x1 conv of a zero vector is its bias.
The full maps are still materialised, in the dense head's planar layout, so post-processing (top-k over the whole
map, including its tie order among the many equal bias scores) sees exactly what the dense head would give it.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from detector.models.grad_layout import conv2d
from detector.ops.gemm import linear, linear_rows, row_buffer, train_linear, uses_onednn
from detector.sparse.tensor import SparseTensor
from detector.sparse.workspace import Workspace

CLS_PRIOR = 0.01  # initial foreground probability of every anchor (focal-loss prior), bias = -log((1 - p) / p)


class HeadOutput(NamedTuple):
    """Raw head maps, indexed channels last: cls (B, H, W, A*K), reg (B, H, W, A*7), dir (B, H, W, A*2). At inference
    they are views of one channel-planar tensor (see :meth:`AnchorHead.forward`), in training contiguous maps."""

    cls: torch.Tensor
    reg: torch.Tensor
    dir: torch.Tensor


class AnchorHead(nn.Module):
    """Dense head. in_channels: neck width (384); num_anchors: A per cell; num_classes: K."""

    def __init__(self, *, in_channels: int, num_anchors: int, num_classes: int) -> None:
        super().__init__()
        self.num_anchors, self.num_classes = num_anchors, num_classes
        self.conv_cls = nn.Conv2d(in_channels, num_anchors * num_classes, 1)
        self.conv_reg = nn.Conv2d(in_channels, num_anchors * 7, 1)
        self.conv_dir = nn.Conv2d(in_channels, num_anchors * 2, 1)
        nn.init.normal_(self.conv_cls.weight, std=0.01)
        nn.init.constant_(self.conv_cls.bias, -math.log((1 - CLS_PRIOR) / CLS_PRIOR))
        nn.init.normal_(self.conv_reg.weight, std=0.01)
        nn.init.zeros_(self.conv_reg.bias)

    def fused(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The three 1x1 convs as one layer: weight (O, C) and bias (O,), rows cls, then reg, then dir
        (O = A*K + A*7 + A*2)."""
        convs = (self.conv_cls, self.conv_reg, self.conv_dir)
        weight = torch.cat([m.weight.view(m.out_channels, m.in_channels) for m in convs])
        return weight, torch.cat([m.bias for m in convs])

    def split(self, out: torch.Tensor) -> HeadOutput:
        """(B, H, W, O) output of :meth:`fused` (any strides) → :class:`HeadOutput` (views of its channel ranges)."""
        n_cls, n_reg = self.conv_cls.out_channels, self.conv_reg.out_channels
        return HeadOutput(out[..., :n_cls], out[..., n_cls : n_cls + n_reg], out[..., n_cls + n_reg :])

    def forward(self, x: torch.Tensor, active: torch.Tensor | None = None,
                workspace: Workspace | None = None) -> HeadOutput:
        """x (B, C, H, W) → :class:`HeadOutput` ((B, H, W, C) views). ``active`` is accepted and unused.
        ``workspace`` (inference): the output is this head's reused buffer, valid until its next call.

        Without autograd (inference) the three convs run as one 1x1 conv of the :meth:`fused` weight: the 384-channel
        map is read once instead of three times (measured 2x faster on a channels-last Matterport map). With autograd
        (training) they stay three convs, so training computes exactly what it computed before the fused path existed.
        In fp32 on the CPU that product is oneDNN's GEMM (``detector.ops.gemm``) with the map's pixels as rows.

        The inference output is channel-planar: (B, H, W, C) views of one (B, O, H, W) tensor, so the class logits
        are one contiguous 0.8 MB block on the Matterport map, which post-processing scans; the interleaved
        (B, H, W, O) output of a channels-last conv is a little faster to write but made it touch all 7.9 MB
        (docs/benchmarks.md, "Shared components").
        """
        if torch.is_grad_enabled():
            # conv2d: the modules' own convs, with the weight gradients DDP expects on a channels-last map
            return HeadOutput(
                conv2d(self.conv_cls, x).permute(0, 2, 3, 1),
                conv2d(self.conv_reg, x).permute(0, 2, 3, 1),
                conv2d(self.conv_dir, x).permute(0, 2, 3, 1),
            )
        weight, bias = self.fused()
        b, _, h, w = x.shape
        # (O, C) @ (C, H*W) per sample: the output is channel-planar, (B, O, H*W), so each map's channels lie in one
        # contiguous block. x.flatten(2) is a view for channels-last and NCHW maps alike (BLAS reads it transposed).
        low = x.dtype in (torch.bfloat16, torch.float16) or torch.is_autocast_enabled(x.device.type)
        rows = x.permute(0, 2, 3, 1)  # (B, H, W, C): contiguous for a channels-last map
        if not low and rows.is_contiguous() and uses_onednn(x, weight):
            # oneDNN (detector.ops.gemm), the pixels as its "weight" operand: weight (O, C) @ rows (H*W, C).t() is
            # the planar (O, H*W) map straight away (Matterport map, trained weights, 2 threads: Head 8.9 ms against
            # 20.6 ms in MKL's baddbmm; tools/bench_gemm.py, docs/sparse.md "GEMM library")
            planes = [linear(weight, rows[i].reshape(h * w, -1)).add_(bias[:, None]) for i in range(b)]
            out = planes[0][None] if b == 1 else torch.stack(planes)
            return self.split(out.unflatten(2, (h, w)).permute(0, 2, 3, 1))
        if workspace is None and not low:
            out = torch.baddbmm(bias[None, :, None], weight.expand(b, -1, -1), x.flatten(2))
        else:
            # out= is not autocast: the map's dtype by hand (bf16 inference); and in bf16 one addmm per sample, as
            # baddbmm's bf16 path ran 23x slower (253 vs 11 ms on the Matterport map, 1 thread)
            dt = torch.get_autocast_dtype(x.device.type) if torch.is_autocast_enabled(x.device.type) else x.dtype
            shape = (b, weight.shape[0], h * w)
            out = x.new_empty(shape, dtype=dt) if workspace is None else workspace.take(self, "out", shape, dt,
                                                                                        x.device)
            wt, bt, xs = weight.to(dt), bias.to(dt)[:, None], x.to(dt).flatten(2)
            if low:
                for i in range(b):
                    torch.addmm(bt, wt, xs[i], out=out[i])
            else:
                torch.baddbmm(bt[None], wt.expand(b, -1, -1), xs, out=out)
        return self.split(out.unflatten(2, (h, w)).permute(0, 2, 3, 1))


    def on_sites(self, rows: SparseTensor) -> HeadOutput:
        """The head of the map that is ``rows.features`` (N, C) at ``rows``' sites and zero elsewhere, computed on those
        sites only: a 1x1 conv of a zero vector is its bias, so each output map is its bias with the N sites' values
        written in. The same values as :meth:`forward` on the scattered map, and the same gradients, for every
        parameter (the bias gets the gradient of every cell) and the rows, without the (B, C, H, W) canvas or its
        gradient. (B, H, W, C) views of channel-planar maps; three products like the training convs
        (``PointPillars.forward`` uses it when the backbone is all sparse and autograd is on)."""
        b, (h, w) = rows.batch_size, rows.spatial_shape
        keys = rows.keys()
        bi = torch.div(keys, h * w, rounding_mode="floor")
        hw = keys - bi * (h * w)
        maps = []
        for conv in (self.conv_cls, self.conv_reg, self.conv_dir):
            o = conv.out_channels
            vals = train_linear(rows.features, conv.weight.view(o, conv.in_channels), conv.bias)  # oneDNN in fp32
            # channel-planar (B, O, H*W) like the inference head: filling each channel's plane with its bias is a
            # contiguous broadcast (an interleaved (B*H*W, O) fill ran 1.5 GB/s); the N sites written in place
            full = conv.bias.to(vals.dtype)[None, :, None].expand(b, o, h * w).clone()
            full.permute(0, 2, 1).index_put_((bi, hw), vals)
            maps.append(full.view(b, o, h, w).permute(0, 2, 3, 1))
        return HeadOutput(*maps)


class SparseExactHead(AnchorHead):
    """The dense head computed on active sites only; exact when ``x`` is zero wherever ``active`` is False."""

    def forward(self, x: torch.Tensor, active: torch.Tensor | None = None,
                workspace: Workspace | None = None) -> HeadOutput:
        """x (B, C, H, W), active (B, H, W) bool → :class:`HeadOutput`; ``active=None`` falls back to the dense path
        (a dense backbone has no inactive sites). ``workspace`` (inference): the output is this head's reused buffer
        (bias everywhere but the last call's active sites, which are reset first), valid until its next call."""
        if active is None:
            return super().forward(x, None, workspace)
        b, c, h, w = x.shape
        weight, bias = self.fused()  # (O, C), (O,): the dense head's own fused layer
        # Gather the active sites' feature vectors: (N_active, C), rows in (b, y, x) order.
        bi, yi, xi = torch.nonzero(active, as_tuple=True)
        if workspace is not None:
            return self._reused(x, bi, yi, xi, weight.to(x.dtype), bias.to(x.dtype), workspace)
        feats = x[bi, :, yi, xi]
        if uses_onednn(feats, weight):  # oneDNN (detector.ops.gemm), at a bucketed row count
            vals = linear_rows(feats, weight, bias)
        else:
            vals = F.linear(feats, weight, bias)  # (N_active, O); bfloat16 under autocast, like the dense head's
        # (B, O, H, W), planar like the dense head's, in the dtype the convs would give (bias rounded as theirs is)
        out = bias.to(vals.dtype)[None, :, None, None].expand(b, -1, h, w).clone()
        out[bi, :, yi, xi] = vals
        return self.split(out.permute(0, 2, 3, 1))

    def _reused(self, x: torch.Tensor, bi: torch.Tensor, yi: torch.Tensor, xi: torch.Tensor, weight: torch.Tensor,
                bias: torch.Tensor, workspace: Workspace) -> HeadOutput:
        """The forward into workspace buffers: gather, one ``addmm``, and the planar output canvas of which only the
        previous call's active sites are reset to the bias."""
        b, c, h, w = x.shape
        o = weight.shape[0]
        rows = x.permute(0, 2, 3, 1)  # (B, H, W, C): a view; a plain reshape for the channels-last map
        n = bi.numel()
        onednn = uses_onednn(x, weight)
        # oneDNN (detector.ops.gemm) runs at a bucketed row count: the gather fills the first n rows of the buffer
        if onednn:
            buf = row_buffer(n, c, x, workspace, self, "feats")
        else:
            buf = workspace.take(self, "feats", (n, c), x.dtype, x.device)
        feats = buf[:n]
        if rows.is_contiguous():
            torch.index_select(rows.view(b * h * w, c), 0, (bi * h + yi) * w + xi, out=feats)
        else:
            feats.copy_(x[bi, :, yi, xi])
        if onednn:
            vals = linear(buf, weight, bias)[:n]  # allocates its output
        else:
            vals = torch.addmm(bias, feats, weight.t(), out=workspace.take(self, "vals", (bi.numel(), o), x.dtype,
                                                                          x.device))
        out = workspace.scatter(self, "out", (b, o, h * w), (bi, yi * w + xi), vals, fill=bias, dims=(0, 2, 1))
        return self.split(out.view(b, o, h, w).permute(0, 2, 3, 1))
