"""Backward passes of the GEMM forms that gather instead of scatter (training; the forward is the plain form).

Autograd's backward of a row gather (``index_select``) is an ``index_add`` into a zero matrix, which CPU torch runs as
a ``scatter_add`` over an expanded index: 40 ms for 5,654 x 64 rows on the 2-core EPYC, most of a sparse training
step (docs/sparse.md, "Training"). Both convs here avoid it:

- :class:`SubMGemm`: a submanifold conv's neighbour relation is symmetric (site j is the neighbour of site i at
  offset d exactly when i is j's neighbour at -d, within one batch item and the grid), so the gradient w.r.t. the
  input is the same SubM over the same table applied to the output gradient, with the kernel flipped in both spatial
  axes and its in / out channels swapped: one gather and one GEMM, like the forward, deterministic on every device.
- :class:`GatherUnique`: a gather whose indices are unique apart from the sentinel zero row (the 2x2 down-conv: each
  input lands in one output slot; the transposed conv's GEMM form: each target reads its own (parent, slot) row), so
  the backward writes each gradient row to its one source row (``index_put`` without accumulation).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from detector.ops.gemm import bucket_rows, linear, uses_onednn


def _taps_matrix(weight: Tensor) -> Tensor:
    """``(O, C, kh, kw)`` → ``(O, kh * kw * C)``, column ``(ky * kw + kx) * C + c`` (``conv.conv_matrix``)."""
    o, c, kh, kw = weight.shape
    return weight.permute(0, 2, 3, 1).reshape(o, kh * kw * c)


def _padded(x: Tensor) -> Tensor:
    return torch.cat([x, x.new_zeros(1, x.shape[1])], dim=0)


class SubMGemm(torch.autograd.Function):
    """``out (N, O) = gather(features padded, index).view(N, K*C) @ conv_matrix(weight).t()`` for a SubM table's
    ``index`` (``SubMTable.padded``), with the mirrored-kernel backward described in the module docstring."""

    @staticmethod
    def forward(ctx: Any, features: Tensor, weight: Tensor, index: Tensor) -> Tensor:
        n = features.shape[0]
        matrix = _taps_matrix(weight)
        ctx.features_dtype = features.dtype
        ctx.onednn = uses_onednn(features, matrix)  # fp32 on the CPU outside autocast (autograd is off in here)
        if ctx.onednn:
            # oneDNN's GEMMs (detector.ops.gemm) at a bucketed row count: the gather fills the first n rows, the
            # rest are zero (the weight gradient sums over every row)
            cols = features.new_empty((bucket_rows(n), matrix.shape[1]))
            torch.index_select(_padded(features), 0, index, out=cols.view(-1, features.shape[1])[: index.numel()])
            cols[n:].zero_()
            ctx.save_for_backward(cols, weight, index)
            return linear(cols, matrix)[:n]
        cols = _padded(features).index_select(0, index).view(n, -1)
        ctx.save_for_backward(cols, weight, index)
        return cols @ matrix.t()  # bf16 under autocast (the backward runs in the gradient's dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad_out: Tensor) -> tuple[Tensor | None, Tensor | None, None]:
        cols, weight, index = ctx.saved_tensors
        o, c, kh, kw = weight.shape
        n, k = grad_out.shape[0], kh * kw
        rows = cols.shape[0]  # n, or in oneDNN the forward's bucketed row count (its rows past n are zero)
        grad_out = grad_out.contiguous()
        dt = grad_out.dtype  # bf16 after an autocast forward: the products run in it, the results in the inputs' dtypes
        onednn = ctx.onednn and dt == torch.float32
        grad_features = grad_weight = None
        if ctx.needs_input_grad[0]:
            # Tap k of the backward is W_{K-1-k}^T (module docstring). Gathering the output gradient in reversed tap
            # order lets the weight enter unflipped, as the (K*O, C) stack of its taps (row k*O + o = W[o, :, k], a
            # copy of C-long rows); the flipped kernel was a strided copy, 0.44 ms for a 256-channel 3x3.
            reversed_index = index.view(n, k).flip(1).reshape(-1)
            stacked = weight.permute(2, 3, 0, 1).reshape(k * o, c)
            g = grad_out.new_empty((rows, k * o))
            torch.index_select(_padded(grad_out), 0, reversed_index, out=g.view(-1, o)[: index.numel()])
            if onednn:  # at the forward's row count (detector.ops.gemm); output rows past n are ignored
                grad_features = linear(g, stacked.t())[:n]
            else:
                grad_features = (g @ stacked.to(dt)).to(ctx.features_dtype)
        if ctx.needs_input_grad[1]:
            # (O, K*C) in (O, kh, kw, C) order, handed back in the weight's (O, C, kh, kw) shape: for a channels-last
            # weight (conv.gemm_weight) these are its own strides
            if onednn:  # the output gradient transposed and zero-padded to the forward's rows (cols' extra rows are 0)
                gt = grad_out.new_empty((o, rows))
                gt[:, :n].copy_(grad_out.t())
                gt[:, n:].zero_()
                gw = linear(gt, cols.t())
            else:
                gw = (grad_out.t() @ cols.to(dt)).to(weight.dtype)
            grad_weight = gw.view(o, kh, kw, c).permute(0, 3, 1, 2)
        return grad_features, grad_weight, None


class GatherUnique(torch.autograd.Function):
    """``src[index]`` for an ``index`` whose entries are unique except the last row of ``src`` (the appended zero
    row, which many entries may name); the backward puts each gradient row back into its one source row."""

    @staticmethod
    def forward(ctx: Any, src: Tensor, index: Tensor) -> Tensor:
        ctx.save_for_backward(index)
        ctx.rows = src.shape[0]
        return src.index_select(0, index)

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None]:
        (index,) = ctx.saved_tensors
        out = grad.new_zeros((ctx.rows, *grad.shape[1:]))
        # no accumulation: rows other than the sentinel are written once; the sentinel's (a constant zero row, whose
        # gradient the caller drops) may be written several times, by any of its entries
        return out.index_put_((index,), grad.contiguous()), None
