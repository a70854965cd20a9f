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

from detector.ops.gemm import linear, row_buffer, train_linear, uses_onednn
from detector.sparse.autograd import GatherUnique, SubMGemm
from detector.sparse.indices import (
    Downsample,
    SubMTable,
    UpTable,
    down_table,
    subm_table,
    up_table,
    wide_down_table,
)
from detector.sparse.modules import SparseModule
from detector.sparse.phases import phase
from detector.sparse.tensor import SparseTensor
from detector.sparse.workspace import Workspace, inference_workspace

ConvAlgorithm = Literal["auto", "gemm", "rulebook"]
SubMAlgorithm = ConvAlgorithm  # the name the SubM conv has always used

# "auto" picks the one-GEMM form when at least this fraction of the (site, offset) pairs exist: the GEMM multiplies
# (1 - fill) zero rows, the per-offset rulebook pays K - 1 small matmuls, an index_add and ~10 more ops per layer
# (Python and dispatch time that does not shrink with threads). Measured on the 2-core AVX-512 EPYC (docs/sparse.md,
# tools/bench_sparse.py forms rows): synthetic layers at 1 thread, rulebook / gemm time 0.6-0.8 at fill 0.45-0.67 and
# 1.0 at 0.82-0.88; at 2 threads 0.89 at fill 0.58; real-frame layers (fill 0.78-0.90) equal at 1 and 2 threads,
# and the whole real-frame backbone at 2 threads 17.8 ms with every such layer in gemm vs 19.4 ms with a 0.85 cut.
GEMM_MIN_FILL = 0.7
# The transposed conv's GEMM form multiplies every coarse site by all s*s slots' weights; "auto" takes it when at
# least this fraction of those products is needed by some target (measured: gemm 1.05x faster at 0.54, 2x slower at
# 0.29, docs/sparse.md).
UP_GEMM_MIN_FILL = 0.5


def _reset_like_torch(weight: Tensor, bias: Tensor | None) -> None:
    # the exact init of nn.Conv2d / nn.ConvTranspose2d.reset_parameters (fan_in is computed from the weight layout)
    nn.init.kaiming_uniform_(weight, a=math.sqrt(5))
    if bias is not None:
        fan_in, _ = nn.init._calculate_fan_in_and_fan_out(weight)
        bound = 1.0 / math.sqrt(fan_in) if fan_in > 0 else 0.0
        nn.init.uniform_(bias, -bound, bound)


def gemm_weight(shape: tuple[int, int, int, int], bias: int) -> tuple[nn.Parameter, nn.Parameter | None]:
    """A conv weight of the dense layout ``shape`` (and a ``(bias,)`` bias unless ``bias`` is 0) with torch's default
    init, the weight stored ``torch.channels_last``.

    The values and the ``(d0, d1, kh, kw)`` shape are ``nn.Conv2d``'s / ``nn.ConvTranspose2d``'s (so state dicts copy
    across), but the memory is ``(d0, kh, kw, d1)``: the GEMM forms then view it as a matrix without a copy
    (:func:`conv_matrix`). The init runs on a contiguous tensor first, so a seed gives the same values as before (an
    in-place init of a channels-last tensor draws in memory order). Re-initialise with :func:`init_weight_`.
    """
    w = torch.empty(shape)
    b = torch.empty(bias) if bias else None
    _reset_like_torch(w, b)
    # (d0, kh, kw, d1) memory seen as (d0, d1, kh, kw): the strides the backward of conv_matrix's permute hands the
    # gradient back with, size-1 kernel dims included (DDP compares strides exactly, see models/grad_layout.py)
    d0, d1, kh, kw = shape
    stored = torch.empty(d0, kh, kw, d1).permute(0, 3, 1, 2)
    stored.copy_(w)
    return nn.Parameter(stored), None if b is None else nn.Parameter(b)


def init_weight_(weight: Tensor, init: object) -> None:
    """Re-initialise ``weight`` in place with ``init`` (an ``nn.init`` function of one tensor) drawing the values a
    contiguous tensor would get, whatever ``weight``'s memory layout."""
    w = torch.empty(weight.shape, dtype=weight.dtype, device=weight.device)
    init(w)  # type: ignore[operator]
    with torch.no_grad():
        weight.copy_(w)


def conv_matrix(weight: Tensor) -> Tensor:
    """``(O, C, kh, kw)`` conv weight → ``(O, kh * kw * C)``: column ``(ky * kw + kx) * C + c`` multiplies channel c of
    the neighbour at offset ``ky * kw + kx``. A view for a channels-last weight (:func:`gemm_weight`), else a copy.

    Tap ``j`` is ``m.view(O, K, C)[:, j]``, an ``(O, C)`` block with unit stride along C, so ``f @ tap.t()`` is a BLAS
    product of a transposed operand with no further copy.
    """
    o, c, kh, kw = weight.shape
    return weight.permute(0, 2, 3, 1).reshape(o, kh * kw * c)


def transposed_matrix(weight: Tensor) -> Tensor:
    """``(C, O, s, s)`` transposed-conv weight → ``(C, s * s * O)``: columns ``slot * O + o`` with slot
    ``ky * s + kx``. A view for a channels-last weight (:func:`gemm_weight`), else a copy."""
    c, o, kh, kw = weight.shape
    return weight.permute(0, 2, 3, 1).reshape(c, kh * kw * o)


def compute_dtype(t: Tensor) -> torch.dtype:
    """The dtype a matmul of ``t`` runs in: the autocast dtype inside ``torch.autocast`` (bf16 inference), else
    ``t``'s. The workspace paths use explicit ``out=`` ops, which autocast does not cast, so they cast themselves."""
    dev = t.device.type
    return torch.get_autocast_dtype(dev) if torch.is_autocast_enabled(dev) else t.dtype


def low_precision(t: Tensor) -> bool:
    """Whether ``t``'s matmuls run in bf16 / fp16 (a half-precision tensor, or under autocast)."""
    return compute_dtype(t) in (torch.bfloat16, torch.float16)


def padded_rows(features: Tensor, workspace: Workspace | None = None, owner: object | None = None) -> Tensor:
    """``(N, C)`` → ``(N + 1, C)`` with a zero last row: the sentinel the gather tables point missing neighbours at.
    With a workspace the rows are cast to :func:`compute_dtype` on the way (bf16 inference gathers half the bytes)."""
    n, c = features.shape
    with phase("gather"):
        if workspace is None:
            return torch.cat([features, features.new_zeros(1, c)], dim=0)
        out = workspace.take(owner, "padded", (n + 1, c), compute_dtype(features), features.device)
        out[:n].copy_(features)
        out[n].zero_()
        return out


def _training(*tensors: Tensor) -> bool:
    """Whether autograd will record these tensors' ops (then the GEMM forms use the gathering backwards of
    ``detector.sparse.autograd``; without autograd, e.g. for an exporter's trace, they are plain Gather + MatMul)."""
    return torch.is_grad_enabled() and any(t.requires_grad for t in tensors)


def gather_gemm(padded: Tensor, index: Tensor, matrix: Tensor, workspace: Workspace | None = None,
                owner: object | None = None, unique: bool = False) -> Tensor:
    """The one GEMM form of every conv with a gather table: rows ``index`` ``(M * K,)`` of ``padded`` ``(N + 1, C)``
    as one ``(M, K * C)`` matrix, times ``matrix.t()`` (``matrix`` ``(O, K * C)``, :func:`conv_matrix`) → ``(M, O)``.

    Only a Gather and a MatMul, no data-dependent branch: the form an exporter writes, with ``index`` built outside
    the graph (``SubMTable.padded``, ``DownTable.gather_index``). ``unique``: every row but the sentinel is gathered
    at most once (the non-overlapping down-conv), so training's backward may write rows instead of adding them.
    """
    c = padded.shape[1]
    o, kc = matrix.shape
    m = index.numel() * c // kc
    w = matrix if workspace is None else matrix.to(padded.dtype)
    if uses_onednn(padded, w):
        # inference in oneDNN (detector.ops.gemm): the gather fills the first m rows of a bucket-sized matrix, the
        # rows past them are ignored (each output row depends on its own input row only)
        with phase("gather"):
            cols = row_buffer(m, kc, padded, workspace, owner, "cols")
            torch.index_select(padded, 0, index, out=cols.view(-1, c)[: index.numel()])
        with phase("gemm"):
            return linear(cols, w)[:m]
    if workspace is None:
        # training's product in oneDNN at a bucketed row count where it applies (detector.ops.gemm.train_linear)
        with phase("gather"):
            rows = GatherUnique.apply(padded, index) if unique and _training(padded) else padded.index_select(0, index)
        with phase("gemm"):
            return train_linear(rows.view(m, kc), matrix)
    with phase("gather"):
        cols = workspace.take(owner, "cols", (index.numel(), c), padded.dtype, padded.device)
        torch.index_select(padded, 0, index, out=cols)
    with phase("gemm"):
        out = workspace.take(owner, "out", (m, o), padded.dtype, padded.device)
        return torch.mm(cols.view(m, kc), w.t(), out=out)


def gemm_gather(features: Tensor, index: Tensor, matrix: Tensor, out_channels: int,
                workspace: Workspace | None = None, owner: object | None = None) -> Tensor:
    """The GEMM form of the transposed conv: every row of ``features`` ``(M, C)`` times every slot's weight
    (``matrix`` ``(C, S * O)``, :func:`transposed_matrix`) as one ``(M, S * O)`` product, viewed as ``(M * S, O)``
    with a zero row appended, then rows ``index`` (``UpTable.gather_index``) → ``(N_target, O)``. MatMul + Gather."""
    m = features.shape[0]
    o = out_channels
    s = matrix.shape[1] // o
    if uses_onednn(features, matrix):
        # inference in oneDNN (detector.ops.gemm): the features and a zero row (whose s products are zero: the
        # sentinel row m * s) in a bucket-sized matrix; rows past them give products no index names
        with phase("gather"):
            rows = row_buffer(m + 1, features.shape[1], features, workspace, owner, "padded")
            rows[:m].copy_(features)
            rows[m].zero_()
        with phase("gemm"):
            prod = linear(rows, matrix.t()).view(-1, o)
        with phase("gather"):
            if workspace is None:
                return prod.index_select(0, index)
            out = workspace.take(owner, "out", (index.numel(), o), features.dtype, features.device)
            return torch.index_select(prod, 0, index, out=out)
    if workspace is None:
        with phase("gemm"):
            prod = torch.cat([train_linear(features, matrix.t()).view(m * s, o), features.new_zeros(1, o)], dim=0)
        with phase("gather"):
            # each target reads its own (parent, slot) row: a unique gather, whose backward writes rows
            return GatherUnique.apply(prod, index) if _training(prod) else prod.index_select(0, index)
    dtype = compute_dtype(features)
    with phase("gemm"):
        prod = workspace.take(owner, "products", (m * s + 1, o), dtype, features.device)
        torch.mm(features.to(dtype), matrix.to(dtype), out=prod[: m * s].view(m, s * o))
        prod[m * s].zero_()
    with phase("gather"):
        out = workspace.take(owner, "out", (index.numel(), o), dtype, features.device)
        return torch.index_select(prod, 0, index, out=out)


def _add_bias(out: Tensor, bias: Tensor | None, in_place: bool) -> Tensor:
    if bias is None:
        return out
    with phase("bn_relu"):
        return out.add_(bias) if in_place else out + bias


def subm_algorithm(algorithm: SubMAlgorithm, table: SubMTable, features: Tensor, weight: Tensor) -> SubMAlgorithm:
    """The form :func:`subm_conv2d` runs: ``algorithm`` unless it is ``"auto"``, which takes ``"gemm"`` from
    ``GEMM_MIN_FILL``, in bf16 (the one GEMM keeps every sum in fp32; the rulebook adds the offsets' bf16 products)
    and wherever the product runs in oneDNN (whose GEMM is 2.2x MKL's on AMD CPUs; the rulebook's per-tap products
    run in MKL), else ``"rulebook"``. ``detector.opcount`` asks it too, to count what runs."""
    if algorithm != "auto":
        return algorithm
    if low_precision(features) or uses_onednn(features, weight):
        return "gemm"
    with phase("table"):
        return "gemm" if table.fill >= GEMM_MIN_FILL else "rulebook"


def subm_conv2d(
    features: Tensor,
    table: SubMTable,
    weight: Tensor,
    bias: Tensor | None = None,
    algorithm: SubMAlgorithm = "auto",
    workspace: Workspace | None = None,
    owner: object | None = None,
) -> Tensor:
    """Submanifold conv of ``features`` ``(N, C)`` over ``table``, ``Conv2d`` weight ``(O, C, k, k)`` → ``(N, O)``.

    ``"gemm"``: gather the K neighbour rows of every site into one ``(N, K*C)`` matrix (missing → the zero row) and
    multiply once by ``(K*C, O)`` (:func:`gather_gemm`). ``"rulebook"``: ``f W_centre`` plus, per other offset, the
    existing pairs' products added into their output rows with ``index_add``. ``workspace`` (inference only): the
    gemm form's buffers are ``owner``'s, reused from frame to frame.
    """
    n, c = features.shape
    o, _, kh, kw = weight.shape
    k = kh * kw
    algorithm = subm_algorithm(algorithm, table, features, weight)
    if algorithm == "gemm" and workspace is None and _training(features, weight):
        # training: the same product, with the backward that gathers (a mirrored SubM) instead of scatter-adding
        with phase("table"):
            index = table.padded
        with phase("gemm"):  # the gather runs inside the autograd function
            out = SubMGemm.apply(features, weight, index)
    elif algorithm == "gemm":
        with phase("table"):
            index = table.padded
        out = gather_gemm(padded_rows(features, workspace, owner), index, conv_matrix(weight), workspace, owner)
    elif algorithm == "rulebook":
        # unbind: one view per tap whose backward stacks the K gradients once (slicing each tap out of the matrix
        # made every tap's backward fill and add a whole (O, K, C) gradient)
        taps = conv_matrix(weight).view(o, k, c).unbind(1)
        centre = k // 2
        with phase("gemm"):
            out = torch.mm(features, taps[centre].t())
        with phase("table"):
            in_rows, out_rows, counts = table.pairs()
        if in_rows.numel():
            with phase("gather"):
                gathered = features.index_select(0, in_rows)
            others = [j for j in range(k) if j != centre]
            with phase("gemm"):
                parts = [torch.mm(g, taps[j].t()) for g, j in zip(gathered.split(counts), others) if g.shape[0]]
            with phase("scatter"):
                # in place into the fresh centre product (mm does not need its output for the backward)
                out.index_add_(0, out_rows, torch.cat(parts, dim=0))
    else:
        raise ValueError(f"unknown SubM algorithm {algorithm!r}")
    return _add_bias(out, bias, workspace is not None)


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
        self.weight, self.bias = gemm_weight((out_channels, in_channels, kernel_size, kernel_size),
                                             out_channels if bias else 0)

    def table(self, x: SparseTensor) -> SubMTable:
        """The neighbour table of ``x``'s sites for this kernel size (cached under ``indice_key`` if one is set)."""
        if self.indice_key is None:
            with phase("table"):
                return subm_table(x.coords, x.spatial_shape, x.lookup(), self.kernel_size)
        key = ("subm", self.indice_key, self.kernel_size)
        t = x.cache.get(key)
        if t is None:
            with phase("table"):
                t = subm_table(x.coords, x.spatial_shape, x.lookup(), self.kernel_size)
            x.cache[key] = t
        return t

    def forward(self, x: SparseTensor) -> SparseTensor:
        if x.features.shape[1] != self.in_channels:
            raise ValueError(f"expected {self.in_channels} input channels, got {x.features.shape[1]}")
        ws = inference_workspace(x.workspace)
        out = subm_conv2d(x.features, self.table(x), self.weight, self.bias, self.algorithm, ws, self)
        return x.replace_feature(out)

    def extra_repr(self) -> str:
        return (
            f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, bias={self.bias is not None}, "
            f"indice_key={self.indice_key!r}"
        )


class SparseConv2d(SparseModule):
    """Strided down-conv to the ``(H//s, W//s)`` grid.

    Kernel = stride = s (the paper's 2x2): output sites ``unique(floor(c / s))``; every input lands in exactly one
    output, at kernel slot ``(iy % s, ix % s)``. ``"gemm"``: each output gathers its ``s*s`` inputs (missing → the zero
    row) into one ``(M, s*s*C)`` matrix, one matmul (:func:`gather_gemm`); ``"rulebook"``: the inputs are scattered
    into that matrix instead (``index_put``, each cell written at most once), then the same matmul.

    Odd kernel k > s (the released code's 9x9 stride-2 Sparse+WideConv down-conv): ``padding = k // 2``; output sites
    are every site whose k x k window holds an input (``indices.wide_down_table``), value ``F.conv2d(dense, w,
    stride=s, padding=k // 2)`` there. ``"gemm"``: the ``(M, k*k*C)`` gather and one matmul; ``"rulebook"``: per
    weight tap, gather, matmul and one ``index_add``.

    Args:
        downsample: for kernel = stride, ``"floor"`` (standard, the paper) or ``"reference_quirk"``
            (MinkowskiEngine's ``expand_coordinates`` output set, as the released code ran it; see
            ``indices.down_table``). An odd kernel has one semantics (it is ME's for odd kernels) and takes
            ``"floor"`` only.
        algorithm: ``"auto" | "gemm" | "rulebook"``; all give the same result. ``"auto"``: kernel = stride takes
            ``"gemm"``; an odd kernel takes ``"gemm"`` when at least ``GEMM_MIN_FILL`` of the (output, tap) cells
            have an input.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int = 2,
        stride: int = 2,
        bias: bool = False,
        downsample: Downsample = "floor",
        algorithm: ConvAlgorithm = "auto",
    ) -> None:
        super().__init__()
        if kernel_size != stride and (kernel_size % 2 != 1 or kernel_size < stride):
            raise ValueError(f"SparseConv2d needs kernel_size == stride or an odd kernel_size > stride, got "
                             f"{kernel_size} and {stride}")
        if downsample not in ("floor", "reference_quirk"):
            raise ValueError(f"unknown downsample mode {downsample!r}")
        if kernel_size != stride and downsample != "floor":
            raise ValueError(f"downsample {downsample!r} applies to kernel_size == stride only")
        if algorithm not in ("auto", "gemm", "rulebook"):
            raise ValueError(f"unknown algorithm {algorithm!r}")
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.kernel_size = kernel_size
        self.stride = stride
        self.downsample: Downsample = downsample
        self.algorithm: ConvAlgorithm = algorithm
        self.weight, self.bias = gemm_weight((out_channels, in_channels, kernel_size, kernel_size),
                                             out_channels if bias else 0)

    def forward(self, x: SparseTensor) -> SparseTensor:
        if x.features.shape[1] != self.in_channels:
            raise ValueError(f"expected {self.in_channels} input channels, got {x.features.shape[1]}")
        k, s, c = self.kernel_size, self.stride, self.in_channels
        ws = inference_workspace(x.workspace)
        kk = k * k
        with phase("table"):
            if k != s:
                t = wide_down_table(x.coords, x.spatial_shape, k, s)
            else:
                t = down_table(x.coords, x.spatial_shape, s, self.downsample)
            algorithm = self.algorithm
            if algorithm == "auto":
                algorithm = "gemm" if k == s or t.fill(kk) >= GEMM_MIN_FILL else "rulebook"
            index = t.gather_index(x.num_active, kk) if algorithm == "gemm" else None
        w = conv_matrix(self.weight)  # (O, k*k*C)
        m = t.out_coords.shape[0]
        if index is not None:
            out = gather_gemm(padded_rows(x.features, ws, self), index, w, ws, self, unique=k == s)
        elif k == s:
            with phase("scatter"):
                f = x.features if t.in_rows.numel() == x.num_active else x.features.index_select(0, t.in_rows)
                # each (output, slot) cell receives at most one input, so index_put (no accumulation) is exact and
                # deterministic
                buf = f.new_zeros(m * kk, c).index_put((t.out_rows * kk + t.slots,), f)
            with phase("gemm"):
                out = buf.view(m, kk * c) @ w.t()
        else:
            out = self._per_tap(x.features, t, w)
        out = _add_bias(out, self.bias, ws is not None)
        return SparseTensor(out, t.out_coords, t.out_shape, x.batch_size, workspace=x.workspace, origin=self)

    def _per_tap(self, features: Tensor, t, w: Tensor) -> Tensor:
        """The wide conv's rulebook: per tap, the products of its (input, output) pairs, added into the output rows."""
        kk = self.kernel_size**2
        taps = w.view(self.out_channels, kk, self.in_channels).unbind(1)  # one backward stack, not kk fills
        with phase("table"):
            order = torch.argsort(t.slots, stable=True)
            counts = torch.bincount(t.slots, minlength=kk).tolist()
        with phase("gather"):
            gathered = features.index_select(0, t.in_rows[order])
        with phase("gemm"):
            parts = [g @ taps[j].t() for j, g in enumerate(gathered.split(counts)) if g.shape[0]]
        if not parts:
            return features.new_zeros(t.out_coords.shape[0], self.out_channels)
        with phase("scatter"):
            prods = torch.cat(parts, dim=0)  # bf16 under autocast
            return prods.new_zeros(t.out_coords.shape[0], self.out_channels).index_add_(0, t.out_rows[order], prods)

    def extra_repr(self) -> str:
        return (
            f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, stride={self.stride}, "
            f"bias={self.bias is not None}, downsample={self.downsample!r}"
        )


def up_algorithm(algorithm: ConvAlgorithm, table: UpTable, num_coarse: int, stride: int, features: Tensor,
                 matrix: Tensor) -> ConvAlgorithm:
    """The form a transposed conv over ``table`` runs: ``algorithm`` unless it is ``"auto"``, which takes ``"gemm"``
    wherever the product runs in oneDNN or at least ``UP_GEMM_MIN_FILL`` of the ``num_coarse * stride**2`` products
    are needed, else ``"rulebook"``. ``detector.opcount`` asks it too, to count what runs."""
    if algorithm != "auto":
        return algorithm
    if uses_onednn(features, matrix):
        return "gemm"
    with phase("table"):
        needed = int((table.parent_rows >= 0).sum())
    return "gemm" if needed >= UP_GEMM_MIN_FILL * num_coarse * stride * stride else "rulebook"


class SparseConvTranspose2d(SparseModule):
    """Transposed conv (kernel = stride = s) evaluated only on a target active set.

    ``forward(x, target)``: for a target site ``q`` the output is ``W[:, :, q_y % s, q_x % s]^T f(floor(q / s))``
    (+ bias), zero (+ bias) where that parent is inactive in ``x``. Weight ``(in, out, s, s)`` as in
    ``ConvTranspose2d``.

    ``"gemm"``: one ``(M, C) x (C, s*s*O)`` product of every coarse site with every slot's weight, then each target
    gathers its row (``parent * s*s + slot``, or an appended zero row; :func:`gemm_gather`). ``"rulebook"``: the
    targets grouped by slot, one ``(n_slot, C) x (C, O)`` product per slot over the targets that have an active
    parent (only the products some target needs), then ``index_copy`` into the output rows. ``"auto"``: ``"gemm"``
    when at least ``UP_GEMM_MIN_FILL`` of the ``M * s*s`` products are needed.
    """

    def __init__(
        self, in_channels: int, out_channels: int, kernel_size: int = 2, stride: int | None = None,
        bias: bool = False, algorithm: ConvAlgorithm = "auto",
    ) -> None:
        super().__init__()
        stride = kernel_size if stride is None else stride
        if kernel_size != stride:
            raise ValueError(f"SparseConvTranspose2d supports kernel_size == stride only, got {kernel_size}, {stride}")
        if algorithm not in ("auto", "gemm", "rulebook"):
            raise ValueError(f"unknown algorithm {algorithm!r}")
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.kernel_size = kernel_size
        self.stride = stride
        self.algorithm: ConvAlgorithm = algorithm
        self.weight, self.bias = gemm_weight((in_channels, out_channels, kernel_size, kernel_size),
                                             out_channels if bias else 0)

    def forward(self, x: SparseTensor, target: SparseTensor) -> SparseTensor:  # type: ignore[override]
        """``x``: coarse input; ``target``: the fine active set (its features are ignored). Returns ``target``'s sites
        with ``out_channels`` features, spatial shape ``target.spatial_shape``."""
        if x.features.shape[1] != self.in_channels:
            raise ValueError(f"expected {self.in_channels} input channels, got {x.features.shape[1]}")
        if x.batch_size != target.batch_size:
            raise ValueError(f"batch sizes differ: input {x.batch_size}, target {target.batch_size}")
        s, c, o = self.stride, self.in_channels, self.out_channels
        ws = inference_workspace(x.workspace)
        w = transposed_matrix(self.weight)  # (C, s*s*O)
        if s == 1 and target.coords is x.coords:
            # same site set: a plain 1x1 matmul
            dt = compute_dtype(x.features)
            if uses_onednn(x.features, w):  # oneDNN (detector.ops.gemm) at a bucketed row count
                with phase("gather"):
                    rows = row_buffer(x.num_active, c, x.features, ws, self)
                    rows[: x.num_active].copy_(x.features)
                with phase("gemm"):
                    out = linear(rows, w.t())[: x.num_active]
            else:
                with phase("gemm"):
                    out = train_linear(x.features, w.t()) if ws is None else torch.mm(
                        x.features.to(dt), w.to(dt), out=ws.take(self, "out", (x.num_active, o), dt, w.device))
        else:
            with phase("table"):
                t = up_table(target.coords, x.spatial_shape, x.lookup(), s)
            algorithm = up_algorithm(self.algorithm, t, x.num_active, s, x.features, w)
            if algorithm == "gemm":
                with phase("table"):
                    index = t.gather_index(x.num_active, s)
                out = gemm_gather(x.features, index, w, o, ws, self)
            else:
                slot_w = w.view(c, s * s, o).unbind(1)
                with phase("table"):
                    rows, parents, counts = t.by_slot(s)
                with phase("gather"):
                    g = x.features.index_select(0, parents)
                with phase("gemm"):
                    parts = [gi @ slot_w[j] for j, gi in enumerate(g.split(counts)) if gi.shape[0]]
                with phase("scatter"):
                    y = torch.cat(parts, dim=0) if parts else g.new_zeros(0, o)
                    # targets without an active parent stay zero (+ bias)
                    out = y.new_zeros(target.num_active, o).index_copy(0, rows, y)
        out = _add_bias(out, self.bias, ws is not None)
        return target.replace_feature(out)

    def extra_repr(self) -> str:
        return (
            f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, stride={self.stride}, "
            f"bias={self.bias is not None}"
        )
