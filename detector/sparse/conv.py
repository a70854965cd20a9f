"""Sparse 2-D convolutions that equal dense ``torch.nn`` convolutions on their active sites.

Every layer keeps the weight layout of its dense twin (``Conv2d``: ``(out, in, kh, kw)``; ``ConvTranspose2d``:
``(in, out, kh, kw)``) and its default initialisation, so ``sparse.weight.copy_(dense.weight)`` is all it takes to
compare the two. The compute is gather → matmul → scatter over neighbour tables (``detector.sparse.indices``); there is
no Python loop over sites, and autograd provides the backward.

Semantics (``x`` zero-filled outside its active sites, ``dense`` = ``x.dense()``):

- ``SubMConv2d``: output sites = input sites; value = ``F.conv2d(dense, w, padding=k // 2)`` at those sites.
- ``SparseConv2d`` (kernel = stride = s): output sites = ``unique(floor(c / s))``; value = ``F.conv2d(dense, w,
  stride=s)`` there (``downsample="reference_quirk"`` changes the output set only, see ``indices.down_table``).
  With an odd kernel k > s: output sites = every site whose window holds an input; value = ``F.conv2d(dense, w,
  stride=s, padding=k // 2)`` there (``indices.wide_down_table``).
- ``SparseConvTranspose2d`` (kernel = stride = s): evaluated on a given target set; value =
  ``F.conv_transpose2d(dense, w, stride=s)`` at the target sites.
"""

from __future__ import annotations

import math
from typing import Literal

import torch
from torch import Tensor, nn

from detector.sparse.indices import Downsample, SubMTable, down_table, subm_table, up_table, wide_down_table
from detector.sparse.modules import SparseModule
from detector.sparse.tensor import SparseTensor

SubMAlgorithm = Literal["auto", "gemm", "rulebook"]

# "auto" picks the one-GEMM im2col path when at least this fraction of the (site, offset) pairs exist. The GEMM then
# multiplies few zero rows and beats K separate small matmuls + index_add; on sparse tables (uniform occupancy, 9x9
# kernels) the per-offset rulebook wastes nothing. Measured on a 2-core CPU with tools/bench_sparse.py (docs/sparse.md).
GEMM_MIN_FILL = 0.7


def _reset_like_torch(weight: Tensor, bias: Tensor | None) -> None:
    # the exact init of nn.Conv2d / nn.ConvTranspose2d.reset_parameters (fan_in is computed from the weight layout)
    nn.init.kaiming_uniform_(weight, a=math.sqrt(5))
    if bias is not None:
        fan_in, _ = nn.init._calculate_fan_in_and_fan_out(weight)
        bound = 1.0 / math.sqrt(fan_in) if fan_in > 0 else 0.0
        nn.init.uniform_(bias, -bound, bound)


def _taps_last(weight: Tensor) -> Tensor:
    """``(O, C, kh, kw)`` conv weight → contiguous ``(O, kh * kw, C)`` (the weight in channels-last order).

    Tap ``j = ky * kw + kx`` is then ``w[:, j]``, an ``(O, C)`` matrix with unit stride along C, so ``f @ w[:, j].t()``
    runs as a BLAS product on a transposed operand without any copy. The copy made here reads the weight with
    stride ``kh * kw`` along its innermost output axis: measured 3.4x cheaper than the ``(kh * kw, C, O)`` layout's
    (0.19 vs 0.63 ms for a 256-channel 3x3 weight, 1 thread), which was about 12 % of the Matterport backbone.
    """
    o, c, kh, kw = weight.shape
    return weight.permute(0, 2, 3, 1).contiguous().view(o, kh * kw, c)


def subm_conv2d(
    features: Tensor, table: SubMTable, weight: Tensor, bias: Tensor | None = None, algorithm: SubMAlgorithm = "auto"
) -> Tensor:
    """Submanifold conv of ``features`` ``(N, C)`` over ``table``, ``Conv2d`` weight ``(O, C, k, k)`` → ``(N, O)``.

    ``"gemm"``: gather the K neighbour rows of every site into one ``(N, K*C)`` matrix (missing → a zero row) and
    multiply once by ``(K*C, O)``. ``"rulebook"``: ``f W_centre`` plus, per other offset, the existing pairs' products
    added into their output rows with ``index_add``.
    """
    n, c = features.shape
    o, _, kh, kw = weight.shape
    k = kh * kw
    if algorithm == "auto":
        algorithm = "gemm" if table.fill >= GEMM_MIN_FILL else "rulebook"
    # (O, C, kh, kw) -> (O, kh * kw, C): column (ky * kw + kx) * C + c multiplies channel c of the neighbour at
    # offset ky * kw + kx
    w = _taps_last(weight)
    if algorithm == "gemm":
        padded = torch.cat([features, features.new_zeros(1, c)], dim=0)
        cols = padded.index_select(0, table.padded).view(n, k * c)
        out = cols @ w.reshape(o, k * c).t()
    elif algorithm == "rulebook":
        centre = k // 2
        out = features @ w[:, centre].t()
        in_rows, out_rows, counts = table.pairs()
        if in_rows.numel():
            gathered = features.index_select(0, in_rows)
            others = [j for j in range(k) if j != centre]
            parts = [g @ w[:, j].t() for g, j in zip(gathered.split(counts), others) if g.shape[0]]
            # in place into the fresh centre product (mm does not need its output for the backward)
            out.index_add_(0, out_rows, torch.cat(parts, dim=0))
    else:
        raise ValueError(f"unknown SubM algorithm {algorithm!r}")
    if bias is not None:
        out = out + bias
    return out


class SubMConv2d(SparseModule):
    """Submanifold ``k`` x ``k`` conv (stride 1, odd ``k``): output sites = input sites.

    Args:
        in_channels, out_channels, kernel_size: as ``nn.Conv2d`` (``padding = k // 2`` implied).
        bias: add a bias (the reference backbone uses none).
        indice_key: share the neighbour table with every other conv of the same key and kernel size on the same site
            set (the table lives in the input tensor's cache, so it never leaks to another set of sites).
        algorithm: ``"auto" | "gemm" | "rulebook"``, see ``subm_conv2d``; all give the same result.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int = 3,
        bias: bool = False,
        indice_key: str | None = None,
        algorithm: SubMAlgorithm = "auto",
    ) -> None:
        super().__init__()
        if kernel_size % 2 != 1:
            raise ValueError(f"SubMConv2d needs an odd kernel_size, got {kernel_size}")
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.kernel_size = kernel_size
        self.indice_key = indice_key
        self.algorithm: SubMAlgorithm = algorithm
        self.weight = nn.Parameter(torch.empty(out_channels, in_channels, kernel_size, kernel_size))
        self.bias = nn.Parameter(torch.empty(out_channels)) if bias else None
        _reset_like_torch(self.weight, self.bias)

    def table(self, x: SparseTensor) -> SubMTable:
        """The neighbour table of ``x``'s sites for this kernel size (cached under ``indice_key`` if one is set)."""
        if self.indice_key is None:
            return subm_table(x.coords, x.spatial_shape, x.lookup(), self.kernel_size)
        key = ("subm", self.indice_key, self.kernel_size)
        t = x.cache.get(key)
        if t is None:
            t = subm_table(x.coords, x.spatial_shape, x.lookup(), self.kernel_size)
            x.cache[key] = t
        return t

    def forward(self, x: SparseTensor) -> SparseTensor:
        if x.features.shape[1] != self.in_channels:
            raise ValueError(f"expected {self.in_channels} input channels, got {x.features.shape[1]}")
        out = subm_conv2d(x.features, self.table(x), self.weight, self.bias, self.algorithm)
        return x.replace_feature(out)

    def extra_repr(self) -> str:
        return (
            f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, bias={self.bias is not None}, "
            f"indice_key={self.indice_key!r}"
        )


class SparseConv2d(SparseModule):
    """Strided down-conv to the ``(H//s, W//s)`` grid.

    Kernel = stride = s (the paper's 2x2): output sites ``unique(floor(c / s))``; every input lands in exactly one
    output, at kernel slot ``(iy % s, ix % s)``; the layer scatters the inputs into an ``(M, s*s*C)`` matrix and does
    one matmul with the ``(s*s*C, O)`` weight.

    Odd kernel k > s (the released code's 9x9 stride-2 Sparse+WideConv down-conv): ``padding = k // 2``; output sites
    are every site whose k x k window holds an input (``indices.wide_down_table``), value ``F.conv2d(dense, w,
    stride=s, padding=k // 2)`` there; computed per weight tap (gather, matmul, one ``index_add``).

    Args:
        downsample: for kernel = stride, ``"floor"`` (standard, the paper) or ``"reference_quirk"``
            (MinkowskiEngine's ``expand_coordinates`` output set, as the released code ran it; see
            ``indices.down_table``). An odd kernel has one semantics (it is ME's for odd kernels) and takes
            ``"floor"`` only.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int = 2,
        stride: int = 2,
        bias: bool = False,
        downsample: Downsample = "floor",
    ) -> None:
        super().__init__()
        if kernel_size != stride and (kernel_size % 2 != 1 or kernel_size < stride):
            raise ValueError(f"SparseConv2d needs kernel_size == stride or an odd kernel_size > stride, got "
                             f"{kernel_size} and {stride}")
        if downsample not in ("floor", "reference_quirk"):
            raise ValueError(f"unknown downsample mode {downsample!r}")
        if kernel_size != stride and downsample != "floor":
            raise ValueError(f"downsample {downsample!r} applies to kernel_size == stride only")
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.kernel_size = kernel_size
        self.stride = stride
        self.downsample: Downsample = downsample
        self.weight = nn.Parameter(torch.empty(out_channels, in_channels, kernel_size, kernel_size))
        self.bias = nn.Parameter(torch.empty(out_channels)) if bias else None
        _reset_like_torch(self.weight, self.bias)

    def forward(self, x: SparseTensor) -> SparseTensor:
        if x.features.shape[1] != self.in_channels:
            raise ValueError(f"expected {self.in_channels} input channels, got {x.features.shape[1]}")
        s, c, o = self.stride, self.in_channels, self.out_channels
        if self.kernel_size != s:
            return self._wide(x)
        t = down_table(x.coords, x.spatial_shape, s, self.downsample)
        m = t.out_coords.shape[0]
        f = x.features if t.in_rows.numel() == x.num_active else x.features.index_select(0, t.in_rows)
        # each (output, slot) cell receives at most one input, so index_put (no accumulation) is exact and deterministic
        buf = f.new_zeros(m * s * s, c).index_put((t.out_rows * (s * s) + t.slots,), f)
        out = buf.view(m, s * s * c) @ _taps_last(self.weight).reshape(o, s * s * c).t()
        if self.bias is not None:
            out = out + self.bias
        return SparseTensor(out, t.out_coords, t.out_shape, x.batch_size)

    def _wide(self, x: SparseTensor) -> SparseTensor:
        """The odd-kernel path: per tap, the products of its (input, output) pairs, added into the output rows."""
        k = self.kernel_size
        t = wide_down_table(x.coords, x.spatial_shape, k, self.stride)
        order = torch.argsort(t.slots, stable=True)
        counts = torch.bincount(t.slots, minlength=k * k).tolist()
        w = _taps_last(self.weight)  # (O, k*k, C)
        gathered = x.features.index_select(0, t.in_rows[order])
        parts = [g @ w[:, j].t() for j, g in enumerate(gathered.split(counts)) if g.shape[0]]
        out = x.features.new_zeros(t.out_coords.shape[0], self.out_channels)
        if parts:
            out = out.index_add(0, t.out_rows[order], torch.cat(parts, dim=0))
        if self.bias is not None:
            out = out + self.bias
        return SparseTensor(out, t.out_coords, t.out_shape, x.batch_size)

    def extra_repr(self) -> str:
        return (
            f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, stride={self.stride}, "
            f"bias={self.bias is not None}, downsample={self.downsample!r}"
        )


class SparseConvTranspose2d(SparseModule):
    """Transposed conv (kernel = stride = s) evaluated only on a target active set.

    ``forward(x, target)``: for a target site ``q`` the output is ``W[:, :, q_y % s, q_x % s]^T f(floor(q / s))``
    (+ bias), zero (+ bias) where that parent is inactive in ``x``. The layer groups the targets by kernel slot and
    does one matmul per slot (only products some target needs). Weight ``(in, out, s, s)`` as in
    ``ConvTranspose2d``.
    """

    def __init__(
        self, in_channels: int, out_channels: int, kernel_size: int = 2, stride: int | None = None, bias: bool = False
    ) -> None:
        super().__init__()
        stride = kernel_size if stride is None else stride
        if kernel_size != stride:
            raise ValueError(f"SparseConvTranspose2d supports kernel_size == stride only, got {kernel_size}, {stride}")
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.kernel_size = kernel_size
        self.stride = stride
        self.weight = nn.Parameter(torch.empty(in_channels, out_channels, kernel_size, kernel_size))
        self.bias = nn.Parameter(torch.empty(out_channels)) if bias else None
        _reset_like_torch(self.weight, self.bias)

    def forward(self, x: SparseTensor, target: SparseTensor) -> SparseTensor:  # type: ignore[override]
        """``x``: coarse input; ``target``: the fine active set (its features are ignored). Returns ``target``'s sites
        with ``out_channels`` features, spatial shape ``target.spatial_shape``."""
        if x.features.shape[1] != self.in_channels:
            raise ValueError(f"expected {self.in_channels} input channels, got {x.features.shape[1]}")
        if x.batch_size != target.batch_size:
            raise ValueError(f"batch sizes differ: input {x.batch_size}, target {target.batch_size}")
        s, o = self.stride, self.out_channels
        # (C, O, s, s) -> (s * s, C, O): slot ky * s + kx as a contiguous (C, O) matrix. At s = 1 a plain view: the
        # permute of a (C, O, 1, 1) weight is "contiguous" already, so its backward handed the gradient back with
        # permuted strides on the size-1 dims, which DDP's bucket views flag ("Grad strides do not match").
        w = (self.weight.view(1, self.in_channels, o) if s == 1
             else self.weight.permute(2, 3, 0, 1).contiguous().view(s * s, self.in_channels, o))
        if s == 1 and target.coords is x.coords:
            out = x.features @ w[0]  # same site set: a plain 1x1 matmul
        else:
            t = up_table(target.coords, x.spatial_shape, x.lookup(), s)
            # Targets grouped by kernel slot: one (n_slot, C) x (C, O) product per slot over the targets that have an
            # active parent. Only the products that some target needs are computed (multiplying every coarse site by
            # all s*s slots costs 4x more at s = 4 on the Matterport map, where a coarse site has about 4 targets).
            rows, parents, counts = t.by_slot(s)
            g = x.features.index_select(0, parents)
            parts = [gi @ w[j] for j, gi in enumerate(g.split(counts)) if gi.shape[0]]
            y = torch.cat(parts, dim=0) if parts else g.new_zeros(0, o)
            # targets without an active parent stay zero (+ bias)
            out = y.new_zeros(target.num_active, o).index_copy(0, rows, y)
        if self.bias is not None:
            out = out + self.bias
        return target.replace_feature(out)

    def extra_repr(self) -> str:
        return (
            f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, stride={self.stride}, "
            f"bias={self.bias is not None}"
        )
