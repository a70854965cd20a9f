"""The sparse network as an exportable graph: the rulebook comes in as inputs, the graph holds Gather + MatMul only.

Exported as the eager code is (``detector.sparse``), the sparse backbone needs Unique, NonZero and ScatterND and
runs slower in ONNX Runtime and OpenVINO than eager (``shared/docs/deployment.md``). Here the neighbour tables are
built outside the graph by :mod:`detector.sparse.indices`, as voxelization is, and handed in as int64 inputs:

| input | shape | what |
|---|---|---|
| ``features`` | (N0, C) float32 | pillar features on the pseudo-image sites (batch 1) |
| ``down{i}`` | (N_i, k*k) int64 | block i's stride-2 down-conv: for output site j and tap t the input row, or N_{i-1} |
| ``subm{i}_k{k}`` | (N_i, k*k) int64 | block i's SubM k x k neighbour table (``SubMTable.padded``), missing = N_i |
| ``up{i}`` (i >= 2) | (N_1,) int64 | neck level i: row ``parent * s*s + slot`` of its per-slot products, or N_i*s*s |
| ``canvas_rows`` (dense head) | (H*W,) int64 | for each cell ``iy * W + ix`` of the head map its block-1 row, or N_1 |

A missing neighbour points at a zero row appended to the gathered matrix (the sentinel row index), so every conv is
``Gather → Reshape (N, K*C) → MatMul`` with its BatchNorm folded into the weight and a bias, then ReLU, and the number
of sites is a dynamic dimension. A transposed neck conv (kernel = stride = s) multiplies every coarse site by all s*s
taps at once, ``(N_i, C) @ (C, s*s*O)``, and each block-1 target gathers its one row. The output is either the exact
sparse head's rows ``head_rows`` (N_1, O) (bias + scatter onto the map happen outside, as in
:class:`detector.models.head.SparseExactHead`), or, for the dense head, the (H*W, 384) canvas gathered row by row at
``canvas_rows`` from the levels with a zero row appended, and the fused 1x1 head over the whole map (one Gemm), ``head``
(1, O, H, W) like :class:`detector.deploy.dense_graph.DenseGraph`'s.

Made for the runtimes (``docs/measurements/export-graph-analysis-2026-12-07.md``): the dense head's canvas is one
Gather, one write of the 151 MB Matterport map, where a zero fill (ConstantOfShape) and a ScatterND, which copied its
input, passed over it more than once; every shape the graph needs but the site counts is a constant (the zero rows,
the reshapes' widths), so no Shape / Gather / Unsqueeze / Concat / ConstantOfShape chain computes it at run time.

Batch 1 (a robot's frame); equal to the eager ``SparseBackboneNeck`` + head on every output (tests: float32, 1e-4).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from detector.models import PointPillars
from detector.models.head import SparseExactHead
from detector.sparse.indices import SiteLookup, down_table, subm_table, up_table, wide_down_table


@dataclass(frozen=True)
class SparseBlockSpec:
    """One sparse block's structure: the down-conv's ``down_kernel`` / ``stride`` / ``downsample`` mode and the
    kernel of each SubM conv in order."""

    down_kernel: int
    stride: int
    downsample: str
    subm_kernels: tuple[int, ...]


@dataclass(frozen=True)
class SparseSpec:
    """What the tables and the graph need to agree on: the blocks, the neck's upsample strides, the pseudo-image
    ``(ny, nx)`` and the head map ``(H, W)``, and whether the head is the exact sparse head (output rows) or dense."""

    blocks: tuple[SparseBlockSpec, ...]
    up_strides: tuple[int, ...]
    input_shape: tuple[int, int]
    head_shape: tuple[int, int]
    exact_head: bool

    def input_names(self) -> list[str]:
        """Graph input names in the order :meth:`SparseGraph.forward` takes them."""
        names = ["features"]
        for i, b in enumerate(self.blocks, start=1):
            names.append(f"down{i}")
            names += [f"subm{i}_k{k}" for k in sorted(set(b.subm_kernels))]
        names += [f"up{i}" for i in range(2, len(self.up_strides) + 1)]
        if not self.exact_head:
            names.append("canvas_rows")
        return names

    @property
    def output_name(self) -> str:
        return "head_rows" if self.exact_head else "head"


def _bn_scale_shift(bn: nn.BatchNorm1d) -> tuple[Tensor, Tensor]:
    """Eval-mode BatchNorm as ``x * scale + shift`` (running statistics), both (C,)."""
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
    return scale, bn.bias - bn.running_mean * scale


def _taps_matrix(weight: Tensor) -> Tensor:
    """``Conv2d`` weight (O, C, kh, kw) → (kh*kw*C, O): row ``tap * C + c`` with ``tap = ky * kw + kx``, the column
    order of a gathered ``(N, K*C)`` neighbour matrix."""
    o, c, kh, kw = weight.shape
    return weight.permute(2, 3, 1, 0).reshape(kh * kw * c, o)


def sparse_spec(model: PointPillars) -> SparseSpec:
    """The structure of an all-sparse ``model`` (``backbone: sparse | sparse_wide | sparse_wide_down``); a
    ``ValueError`` for the sparse + dense ablations, whose dense tail is not a gather graph."""
    bb = model.backbone
    if not model.sparse_input or bb.sparse_blocks != len(bb.blocks):
        raise ValueError("the sparse export takes an all-sparse backbone (sparse, sparse_wide, sparse_wide_down), "
                         "not the sparse + dense ablations")
    blocks = []
    for block in bb.blocks:
        down = block[0]
        subms = [m.kernel_size for m in list(block)[3::3]]
        blocks.append(SparseBlockSpec(down.kernel_size, down.stride, down.downsample, tuple(subms)))
    strides = tuple(d.deconv.stride for d in bb.deblocks)
    ny, nx = model.output_shape
    s0 = blocks[0].stride
    return SparseSpec(tuple(blocks), strides, (ny, nx), (ny // s0, nx // s0),
                      isinstance(model.anchor_head, SparseExactHead))


class SparseGraph(nn.Module):
    """Sparse backbone + neck + head of an all-sparse :class:`PointPillars` over prebuilt tables (see the module)."""

    def __init__(self, model: PointPillars) -> None:
        super().__init__()
        self.spec = sparse_spec(model)
        bb = model.backbone
        # per block: [(table input name, index of its (K*C, O) weight, then (O,) bias, C)] for the down-conv, then
        # each SubM conv
        self.layers: list[list[tuple[str, int, int]]] = []
        params = nn.ParameterList()
        for i, block in enumerate(bb.blocks, start=1):
            mods = list(block)
            layers = []
            for j in range(0, len(mods), 3):
                conv, bn = mods[j], mods[j + 1]
                scale, shift = _bn_scale_shift(bn)
                w = _taps_matrix(conv.weight) * scale[None, :]
                b = shift if conv.bias is None else conv.bias * scale + shift
                name = f"down{i}" if j == 0 else f"subm{i}_k{conv.kernel_size}"
                layers.append((name, len(params), conv.in_channels))
                params.append(nn.Parameter(w.detach().clone(), requires_grad=False))
                params.append(nn.Parameter(b.detach().clone(), requires_grad=False))
            self.layers.append(layers)
        # neck levels: (C, s*s*O) weight (column slot * O + o, BN scale folded) and the BN shift added after the gather
        self.ups: list[tuple[int, int]] = []
        for d in bb.deblocks:
            s = d.deconv.stride
            scale, shift = _bn_scale_shift(d.norm)
            c, o = d.deconv.weight.shape[:2]
            w = d.deconv.weight.permute(0, 2, 3, 1) * scale  # (C, s, s, O)
            b = shift if d.deconv.bias is None else d.deconv.bias * scale + shift
            self.ups.append((len(params), s))
            params.append(nn.Parameter(w.reshape(c, s * s * o).detach().clone(), requires_grad=False))
            params.append(nn.Parameter(b.detach().clone(), requires_grad=False))
        weight, bias = model.anchor_head.fused()
        self.head_index = len(params)
        params.append(nn.Parameter(weight.t().detach().clone(), requires_grad=False))  # (384, O)
        params.append(nn.Parameter(bias.detach().clone(), requires_grad=False))
        self.params = params
        # (rows, columns) of each weight as Python ints, so the tracer writes them as constants, not Shape ops
        self.widths = {i: (int(w.shape[0]), int(w.shape[1])) for i, w in enumerate(params) if w.dim() == 2}
        self.eval()

    @staticmethod
    def _pad(x: Tensor, channels: int) -> Tensor:
        """``x`` (N, channels) with a zero row appended at N (the sentinel row); the zero row is a constant."""
        return torch.cat([x, torch.zeros(1, channels, dtype=x.dtype, device=x.device)], dim=0)

    def _gather_matmul(self, x: Tensor, table: Tensor, p: int, channels: int) -> Tensor:
        """relu(Gather(x + zero row, table) reshaped (N, K*C) @ weight + bias): one sparse conv + BN + ReLU over ``x``
        (N, C = ``channels``)."""
        kc = self.widths[p][0]
        cols = self._pad(x, channels).index_select(0, table.reshape(-1)).reshape(-1, kc)
        return torch.relu(cols @ self.params[p] + self.params[p + 1])

    def forward(self, *inputs: Tensor) -> Tensor:
        """The tensors named by :meth:`SparseSpec.input_names`, in that order → ``head_rows`` (N_1, O) or ``head``
        (1, O, H, W)."""
        feed = dict(zip(self.spec.input_names(), inputs, strict=True))
        x = feed["features"]
        outs = []
        for layers in self.layers:
            for name, p, channels in layers:
                x = self._gather_matmul(x, feed[name], p, channels)
            outs.append(x)
        levels = []
        for i, ((p, s), coarse) in enumerate(zip(self.ups, outs)):
            w, b = self.params[p], self.params[p + 1]
            if s == 1:  # the block-1 level: a 1x1 conv on the target set itself
                levels.append(torch.relu(coarse @ w + b))
                continue
            o = self.widths[p][1] // (s * s)
            per_slot = self._pad((coarse @ w).reshape(-1, o), o)  # row parent * s*s + slot; a missing parent: zero
            levels.append(torch.relu(per_slot.index_select(0, feed[f"up{i + 1}"]) + b))
        cat = torch.cat(levels, dim=1)  # (N_1, 384)
        wh, bh = self.params[self.head_index], self.params[self.head_index + 1]
        if self.spec.exact_head:
            return cat @ wh + bh
        # the dense head over the whole map: the canvas gathered in one pass (a zero row at every inactive cell), then
        # the 1x1 conv as (O, 384) @ (H*W, 384)^T, planar (O, H*W) straight away (one Gemm with transB, no Transpose
        # of its output), the orientation the eager head gives oneDNN
        c, o = self.widths[self.head_index]
        h, w = self.spec.head_shape
        canvas = self._pad(cat, c).index_select(0, feed["canvas_rows"])  # (H*W, 384)
        return (wh.t() @ canvas.t() + bh[:, None]).reshape(1, o, h, w)


def _flat(coords: Tensor, shape: tuple[int, int]) -> Tensor:
    """``(N, 3)`` ``[b, iy, ix]`` → flat keys ``(b * H + iy) * W + ix``."""
    return (coords[:, 0] * shape[0] + coords[:, 1]) * shape[1] + coords[:, 2]


@dataclass(frozen=True)
class SparseTables:
    """The graph inputs of one frame (:meth:`SparseSpec.input_names` → int64 / float32 tensors) and the block-1
    sites ``(N_1, 3)`` ``[b, iy, ix]`` where the head rows land."""

    inputs: dict[str, Tensor]
    sites: Tensor


def build_tables(spec: SparseSpec, features: Tensor, coords: Tensor) -> SparseTables:
    """The rulebook of one frame (batch 1): pillar ``features`` (N0, C) at ``coords`` (N0, 3) int64 ``[0, iy, ix]``
    on the pseudo-image → :class:`SparseTables`. Built by :mod:`detector.sparse.indices`, outside the graph."""
    inputs: dict[str, Tensor] = {"features": features}
    shape, n = spec.input_shape, coords.shape[0]
    levels: list[tuple[Tensor, tuple[int, int], SiteLookup]] = []
    for i, b in enumerate(spec.blocks, start=1):
        if b.down_kernel == b.stride:
            t = down_table(coords, shape, b.stride, b.downsample)
        else:
            t = wide_down_table(coords, shape, b.down_kernel, b.stride)
        m, k2 = t.out_coords.shape[0], b.down_kernel * b.down_kernel
        # each (output, tap) pair has at most one input, so the gather table is a plain assignment
        g = torch.full((m * k2,), n, dtype=torch.int64, device=coords.device)
        g[t.out_rows * k2 + t.slots] = t.in_rows
        inputs[f"down{i}"] = g.view(m, k2)
        coords, shape, n = t.out_coords, t.out_shape, m
        lookup = SiteLookup(_flat(coords, shape), shape, 1)
        for k in sorted(set(b.subm_kernels)):
            inputs[f"subm{i}_k{k}"] = subm_table(coords, shape, lookup, k).padded.view(m, k * k)
        levels.append((coords, shape, lookup))
    target = levels[0][0]
    for i, s in enumerate(spec.up_strides[1:], start=2):
        _, shape_i, lookup_i = levels[i - 1]
        u = up_table(target, shape_i, lookup_i, s)
        sentinel = levels[i - 1][0].shape[0] * s * s
        inputs[f"up{i}"] = torch.where(u.parent_rows >= 0, u.parent_rows * (s * s) + u.slots,
                                       torch.full_like(u.parent_rows, sentinel))
    if not spec.exact_head:
        h, w = spec.head_shape
        rows = torch.full((h * w,), target.shape[0], dtype=torch.int64, device=target.device)
        rows[target[:, 1] * w + target[:, 2]] = torch.arange(target.shape[0], device=target.device)
        inputs["canvas_rows"] = rows
    return SparseTables({k: inputs[k] for k in spec.input_names()}, target)
