"""spconv 2.x (its CPU build) as a peer of our sparse engine on Sparse PointPillars' sparse backbone + neck.

:class:`SpconvBackboneNeck` is our :class:`~detector.models.sparse_backbone.SparseBackboneNeck` rebuilt layer by layer
in spconv with **our module's weights** (converted to spconv's layout) on the same active sites:

- block i: ``SparseConv2d(2, stride 2)`` (indice key ``down{i}``) → ``BatchNorm1d`` → ``ReLU`` → L_i x (``SubMConv2d``
  (k, padding k // 2; the block's SubMs share one indice key per kernel size) → ``BatchNorm1d`` → ``ReLU``); the
  BatchNorms are ``nn.BatchNorm1d`` with our ``SparseBatchNorm``'s state dict (the same class underneath), eval mode;
- neck level 0 (u = 1): spconv's 1x1 ``SubMConv2d``; level 1 (u = 2): ``SparseInverseConv2d`` on block 2's down-conv
  key, whose output sites are exactly the block-1 sites; level i >= 2 (u = 2**i): ``SparseConvTranspose2d(u, stride
  u)``, which writes all u*u children of every coarse site, then the block-1 sites' rows picked out of them
  (:func:`select_rows`, a sort + searchsorted in torch: spconv has no conv onto a given site set); each level then
  ``BatchNorm1d`` + ``ReLU``, the levels concatenated on the block-1 sites (384 channels), as our ``neck_rows``.

Weight layouts (checked against dense convolution in tests/test_spconv_peer.py): spconv 2.3 stores every conv weight
KRSC, ``(out, kh, kw, in)``; our ``Conv2d`` layout ``(O, C, kh, kw)`` becomes ``w.permute(0, 2, 3, 1)``
(:func:`conv_krsc`); our ``ConvTranspose2d`` layout ``(C, O, s, s)`` becomes ``w.permute(1, 2, 3, 0)`` for the
inverse and the transposed conv (:func:`transposed_krsc`; spconv's kernel offset of a child q of coarse site p is
``q - s p``, the slot ``ConvTranspose2d`` uses). The exception is spconv's 1x1 ``SubMConv2d``, whose fast path
multiplies by ``weight.view(in, out)``, i.e. reads the KRSC tensor's memory as an ``(in, out)`` matrix
(spconv/pytorch/conv.py, ``conv1x1``): :func:`one_by_one_weight` stores the ``(C, O)`` matrix there.

Measures (:func:`exactness`): on the same frame, in float64 (spconv's CPU kernels dispatch float and double), the
max abs difference of spconv's rows and ours site by site (:func:`max_abs_on_sites`, after checking both engines
give the same site sets), and of ours and the masked dense-convolution chain (:func:`dense_reference`: ``F.conv2d`` /
``F.conv_transpose2d`` on zero-filled canvases, the active masks applied after every layer); in float32 each engine
against the float64 dense chain. Determinism (bitwise equality of two identical calls) is measured by
``tools/bench_spconv.py`` on every timed call. spconv is optional (the ``spconv`` extra); :func:`import_spconv` fails
with one line naming the install command. See docs/sparse.md, "spconv as a peer".
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass
from types import ModuleType

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from detector.bench.density import site_frames
from detector.config import ExperimentConfig
from detector.data.experiment import load_eval_frames
from detector.models import PointPillars
from detector.models.sparse_backbone import SparseBackboneNeck, SparseUpsample
from detector.sparse import SparseBatchNorm, SparseConv2d, SparseTensor, SubMConv2d
from detector.sparse.indices import flat_keys
from mpchair.core.errors import InputError

#: How to get spconv: the optional extra (pyproject.toml; its pins in constraints.txt).
SPCONV_INSTALL = "pip install -c constraints.txt -e '.[spconv]'"


def import_spconv() -> ModuleType:
    """``spconv.pytorch``; an :class:`InputError` (one line with the install command) where spconv is missing."""
    try:
        import spconv.pytorch as sp
    except Exception as e:  # ImportError, or a broken install (its compiled core failing to load)
        raise InputError(f"the spconv peer needs spconv 2.3 (its CPU build): {SPCONV_INSTALL} ({e})") from e
    return sp


def spconv_version() -> str:
    """The installed spconv version (``import_spconv`` first)."""
    import spconv

    return str(spconv.__version__)


# --- weight layouts ---------------------------------------------------------------------------------------------

def conv_krsc(weight: Tensor) -> Tensor:
    """Our ``Conv2d``-layout weight ``(O, C, kh, kw)`` → spconv's KRSC ``(O, kh, kw, C)`` (contiguous)."""
    return weight.detach().permute(0, 2, 3, 1).contiguous()


def transposed_krsc(weight: Tensor) -> Tensor:
    """Our ``ConvTranspose2d``-layout weight ``(C, O, s, s)`` → spconv's KRSC ``(O, s, s, C)`` of its inverse /
    transposed conv (contiguous)."""
    return weight.detach().permute(1, 2, 3, 0).contiguous()


def one_by_one_weight(weight: Tensor) -> Tensor:
    """A 1x1 ``ConvTranspose2d`` weight ``(C, O, 1, 1)`` → the ``(O, 1, 1, C)`` tensor whose memory, read as
    ``(C, O)`` (spconv's 1x1 path: ``features @ weight.view(in, out)``), is our ``(C, O)`` matrix."""
    c, o = weight.shape[:2]
    return weight.detach()[:, :, 0, 0].contiguous().view(o, 1, 1, c)


def check_expressible(ours: SparseBackboneNeck) -> None:
    """:class:`InputError` unless spconv can express ``ours`` layer for layer: every block sparse with a 2x2 stride-2
    down-conv on ``floor`` sites (the ablations' dense tails, the 9x9 down-conv and ME's ``reference_quirk`` sites are
    not rebuilt here)."""
    if not ours.all_sparse:
        raise InputError("the spconv peer rebuilds the all-sparse backbone only (sparse_blocks = number of blocks)")
    for block in ours.blocks:
        down = block[0]
        if down.kernel_size != 2 or down.stride != 2 or down.downsample != "floor":
            raise InputError(f"the spconv peer rebuilds 2x2 stride-2 'floor' down-convs only, got kernel "
                             f"{down.kernel_size}, stride {down.stride}, downsample {down.downsample!r}")


# --- the spconv network --------------------------------------------------------------------------------------------

def _norm(bn: SparseBatchNorm) -> nn.BatchNorm1d:
    out = nn.BatchNorm1d(bn.num_features, eps=bn.eps, momentum=bn.momentum)
    out.load_state_dict(bn.state_dict())
    return out


class SpconvBackboneNeck(nn.Module):
    """``ours`` rebuilt in spconv with its weights (module docstring), eval mode, in ``ours``' dtype.

    :meth:`blocks_forward`: input ``SparseConvTensor`` → every block's output; :meth:`neck_rows`: → (block-1 tensor,
    its ``(N_1, sum(out_channels))`` concatenated level features), the rows our ``neck_rows`` gives."""

    def __init__(self, ours: SparseBackboneNeck) -> None:
        super().__init__()
        check_expressible(ours)
        sp = import_spconv()
        dtype = next(ours.parameters()).dtype
        blocks = []
        for i, block in enumerate(ours.blocks, start=1):
            layers: list[nn.Module] = []
            for layer in block:
                if isinstance(layer, SparseConv2d):
                    m = sp.SparseConv2d(layer.in_channels, layer.out_channels, 2, stride=2, bias=False,
                                        indice_key=f"down{i}")
                    m.weight.data = conv_krsc(layer.weight)
                elif isinstance(layer, SubMConv2d):
                    k = layer.kernel_size
                    m = sp.SubMConv2d(layer.in_channels, layer.out_channels, k, padding=k // 2, bias=False,
                                      indice_key=f"subm{i}k{k}")
                    m.weight.data = conv_krsc(layer.weight)
                elif isinstance(layer, SparseBatchNorm):
                    m = _norm(layer)
                else:
                    m = nn.ReLU()
                layers.append(m)
            blocks.append(sp.SparseSequential(*layers))
        self.blocks = nn.ModuleList(blocks)
        levels = []
        for i, deblock in enumerate(ours.deblocks):
            assert isinstance(deblock, SparseUpsample)
            d = deblock.deconv
            if d.stride == 1:
                m = sp.SubMConv2d(d.in_channels, d.out_channels, 1, bias=False)
                m.weight.data = one_by_one_weight(d.weight)
            elif i == 1:
                m = sp.SparseInverseConv2d(d.in_channels, d.out_channels, 2, indice_key="down2", bias=False)
                m.weight.data = transposed_krsc(d.weight)
            else:
                m = sp.SparseConvTranspose2d(d.in_channels, d.out_channels, d.stride, stride=d.stride, bias=False)
                m.weight.data = transposed_krsc(d.weight)
            levels.append(nn.ModuleList([m, _norm(deblock.norm), nn.ReLU()]))
        self.levels = nn.ModuleList(levels)
        self.to(dtype).eval()

    def blocks_forward(self, x):  # SparseConvTensor → list[SparseConvTensor]
        """Every block's output tensor, block 1 first."""
        outs = []
        for block in self.blocks:
            x = block(x)
            outs.append(x)
        return outs

    def neck_rows(self, x) -> tuple[object, Tensor]:
        """(block-1 ``SparseConvTensor``, the levels' features concatenated on its rows)."""
        outs = self.blocks_forward(x)
        target = outs[0]
        feats = []
        for i, (conv, norm, act) in enumerate(self.levels):
            y = conv(outs[i])
            f = y.features
            if i >= 2:  # the transposed conv wrote every child of every coarse site: keep the block-1 sites
                f = f.index_select(0, select_rows(y.indices, target.indices, target.spatial_shape))
            feats.append(act(norm(f)))
        return target, torch.cat(feats, dim=1)


def select_rows(indices: Tensor, targets: Tensor, spatial_shape: Sequence[int]) -> Tensor:
    """Row of ``indices`` ``(N, 3)`` ``[b, iy, ix]`` at each ``targets`` row (every target must be present):
    ``(M,)`` int64. Sort + searchsorted on flat site keys."""
    shape = (int(spatial_shape[0]), int(spatial_shape[1]))
    keys = flat_keys(indices.long(), shape)
    order = torch.argsort(keys)
    pos = torch.searchsorted(keys[order], flat_keys(targets.long(), shape))
    return order[pos.clamp_max(keys.numel() - 1)]


# --- inputs ------------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class SiteFrame:
    """One frame's pillar sites: ``features`` ``(P, C)`` float32 (the pillar net's output, or synthetic) at ``coords``
    ``(P, 3)`` int64 ``[0, iy, ix]`` of the model's pseudo-image grid; ``name`` (frame id or ``synthetic-k``)."""

    name: str
    features: Tensor
    coords: Tensor


@torch.no_grad()
def dataset_frames(net: PointPillars, cfg: ExperimentConfig, data: str, split: str, frames: int) -> list[SiteFrame]:
    """The first ``frames`` frames of ``split`` through ``net``'s voxelizer and pillar net (eval, float32)."""
    out = []
    for f in load_eval_frames(cfg, data, split, frames):
        features, coords = net.pillar_net(net.voxelize([torch.from_numpy(f.points)]))
        out.append(SiteFrame(f.frame_id, features.contiguous(), coords))
    return out


def synthetic_frames(shape: tuple[int, int], density: float, frames: int, channels: int,
                     seed: int = 0) -> list[SiteFrame]:
    """``frames`` clustered site sets at ``density`` with features in [0, 1)
    (:func:`detector.bench.density.site_frames`, frame k seeded ``seed + k``)."""
    return [SiteFrame(f"synthetic-{k}", f, c) for k, (f, c) in enumerate(site_frames(shape, density, frames, channels,
                                                                                     seed))]


def randomise_batchnorm_(module: nn.Module, seed: int) -> None:
    """Seeded non-trivial BatchNorm affine parameters and running statistics (random-weight models otherwise have
    BN = identity, which would leave the BN conversion untested)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in module.modules():
            if isinstance(m, nn.modules.batchnorm._BatchNorm):
                n, dt = m.num_features, m.weight.dtype
                m.weight.copy_(0.5 + torch.rand(n, generator=g).to(dt))
                m.bias.copy_(0.1 * torch.randn(n, generator=g).to(dt))
                m.running_mean.copy_(0.1 * torch.randn(n, generator=g).to(dt))
                m.running_var.copy_(0.5 + torch.rand(n, generator=g).to(dt))


def our_input(frame: SiteFrame, shape: Sequence[int], dtype: torch.dtype = torch.float32, workspace=None,
              origin: object | None = None) -> SparseTensor:
    """``frame`` as our ``SparseTensor`` (batch 1) in ``dtype``."""
    return SparseTensor(frame.features.to(dtype), frame.coords, tuple(shape), 1, workspace=workspace, origin=origin)


def spconv_input(frame: SiteFrame, shape: Sequence[int], dtype: torch.dtype = torch.float32):
    """``frame`` as spconv's ``SparseConvTensor`` (batch 1, int32 indices) in ``dtype``."""
    sp = import_spconv()
    return sp.SparseConvTensor(frame.features.to(dtype).contiguous(), frame.coords.int().contiguous(),
                               [int(shape[0]), int(shape[1])], 1)


def our_blocks(ours: SparseBackboneNeck, x: SparseTensor) -> list[SparseTensor]:
    """Every sparse block's output, block 1 first."""
    outs = []
    for block in ours.blocks:
        x = block(x)
        outs.append(x)
    return outs


# --- exactness ---------------------------------------------------------------------------------------------------

def max_abs_on_sites(coords_a: Tensor, feats_a: Tensor, coords_b: Tensor, feats_b: Tensor,
                     shape: Sequence[int]) -> float:
    """Max abs difference of two feature sets on the same sites (rows in any order, compared site by site, in
    float64); a :class:`ValueError` if the site sets differ."""
    hw = (int(shape[0]), int(shape[1]))
    ka, kb = flat_keys(coords_a.long(), hw), flat_keys(coords_b.long(), hw)
    oa, ob = torch.argsort(ka), torch.argsort(kb)
    if not torch.equal(ka[oa], kb[ob]):
        raise ValueError(f"the site sets differ ({ka.numel()} vs {kb.numel()} sites)")
    if ka.numel() == 0:
        return 0.0
    return float((feats_a[oa].double() - feats_b[ob].double()).abs().max())


def rows_at(canvas: Tensor, coords: Tensor) -> Tensor:
    """``(N, C)`` rows of a ``(B, C, H, W)`` canvas at ``coords`` ``[b, iy, ix]``."""
    c = coords.long()
    return canvas[c[:, 0], :, c[:, 1], c[:, 2]]


def _masked_bn(d: Tensor, mask: Tensor, bn: nn.modules.batchnorm._BatchNorm) -> Tensor:
    """Eval-mode BatchNorm of a dense map, zero off ``mask`` ``(B, H, W)``."""
    y = F.batch_norm(d, bn.running_mean, bn.running_var, bn.weight, bn.bias, False, 0.0, bn.eps)
    return y * mask[:, None]


@torch.no_grad()
def dense_reference(ours: SparseBackboneNeck, x: SparseTensor) -> tuple[list[tuple[Tensor, Tensor]], Tensor]:
    """``ours`` (all-sparse, eval mode) computed with dense ops on zero-filled canvases, the active masks applied
    after every layer: ([(block mask (B, H_i, W_i), block map (B, C_i, H_i, W_i))], neck map (B, 384, H_1, W_1)).

    Masks: a 2x2 stride-2 down-conv's output sites are ``floor(c / 2)`` of its input sites (a 2x2 max-pool of the
    mask); a SubM keeps its sites. The neck levels are ``F.conv_transpose2d`` masked to the block-1 sites."""
    check_expressible(ours)
    d, mask = x.dense(), x.active_mask()
    blocks = []
    for block in ours.blocks:
        for layer in block:
            if isinstance(layer, SparseConv2d):
                mask = F.max_pool2d(mask[:, None].to(d.dtype), 2)[:, 0] > 0
                d = F.conv2d(d, layer.weight, stride=2) * mask[:, None]
            elif isinstance(layer, SubMConv2d):
                d = F.conv2d(d, layer.weight, padding=layer.kernel_size // 2) * mask[:, None]
            elif isinstance(layer, SparseBatchNorm):
                d = _masked_bn(d, mask, layer)
            else:
                d = F.relu(d)
        blocks.append((mask, d))
    m1 = blocks[0][0]
    levels = []
    for deblock, (_, o) in zip(ours.deblocks, blocks):
        u = F.conv_transpose2d(o, deblock.deconv.weight, stride=deblock.deconv.stride) * m1[:, None]
        levels.append(F.relu(_masked_bn(u, m1, deblock.norm)))
    return blocks, torch.cat(levels, dim=1)


@dataclass(frozen=True)
class Outputs:
    """One engine's outputs on a frame: per block (coords (N_i, 3), features (N_i, C_i)) and the neck rows on the
    block-1 sites (coords, features (N_1, 384))."""

    blocks: tuple[tuple[Tensor, Tensor], ...]
    neck: tuple[Tensor, Tensor]


@torch.no_grad()
def run_ours(ours: SparseBackboneNeck, frame: SiteFrame, shape: Sequence[int], dtype: torch.dtype) -> Outputs:
    """Our engine on ``frame`` in ``dtype`` without a workspace (fresh tensors)."""
    blocks = our_blocks(ours, our_input(frame, shape, dtype))
    neck = ours.neck_rows(our_input(frame, shape, dtype))
    return Outputs(tuple((b.coords, b.features) for b in blocks), (neck.coords, neck.features))


@torch.no_grad()
def run_spconv(peer: SpconvBackboneNeck, frame: SiteFrame, shape: Sequence[int], dtype: torch.dtype) -> Outputs:
    """spconv on ``frame`` in ``dtype`` (the peer must be in ``dtype``)."""
    blocks = peer.blocks_forward(spconv_input(frame, shape, dtype))
    target, feats = peer.neck_rows(spconv_input(frame, shape, dtype))
    return Outputs(tuple((b.indices, b.features) for b in blocks), (target.indices, feats))


def _diffs(a: Outputs, b: Outputs, shapes: Sequence[Sequence[int]]) -> dict:
    """Max abs differences of two engines' outputs: per block and of the neck rows."""
    return {"blocks": [max_abs_on_sites(ca, fa, cb, fb, s) for (ca, fa), (cb, fb), s in zip(a.blocks, b.blocks,
                                                                                          shapes)],
            "neck": max_abs_on_sites(*a.neck, *b.neck, shapes[0])}


def _dense_outputs(ours: SparseBackboneNeck, frame: SiteFrame, shape: Sequence[int], on: Outputs) -> Outputs:
    """The float64 dense chain's rows on the sites of ``on``."""
    blocks, neck = dense_reference(ours, our_input(frame, shape, torch.float64))
    return Outputs(tuple((c, rows_at(d, c)) for (c, _), (_, d) in zip(on.blocks, blocks)),
                   (on.neck[0], rows_at(neck, on.neck[0])))


def exactness(ours: SparseBackboneNeck, frame: SiteFrame, shape: Sequence[int], with_spconv: bool = True) -> dict:
    """Max abs differences on ``frame`` (per block, and the neck rows): float64 ours vs the dense chain and spconv vs
    ours; float32 ours and spconv vs the float64 dense chain. ``with_spconv=False``: our side only (no spconv
    needed). ``ours`` is copied (float64 / float32 twins), not changed."""
    ours64 = copy.deepcopy(ours).double().eval()
    ours32 = copy.deepcopy(ours).float().eval()
    shapes = [tuple(shape)] + [(shape[0] >> i, shape[1] >> i) for i in range(1, len(ours.blocks) + 1)]
    out_shapes = shapes[1:]
    o64 = run_ours(ours64, frame, shape, torch.float64)
    dense = _dense_outputs(ours64, frame, shape, o64)
    o32 = run_ours(ours32, frame, shape, torch.float32)
    result = {"sites": [int(c.shape[0]) for c, _ in o64.blocks],
              "float64": {"ours_vs_dense": _diffs(o64, dense, out_shapes)},
              "float32": {"ours_vs_dense64": _diffs(o32, dense, out_shapes)}}
    if with_spconv:
        s64 = run_spconv(SpconvBackboneNeck(ours64), frame, shape, torch.float64)
        s32 = run_spconv(SpconvBackboneNeck(ours32), frame, shape, torch.float32)
        result["float64"]["spconv_vs_ours"] = _diffs(s64, o64, out_shapes)
        result["float64"]["spconv_vs_dense"] = _diffs(s64, dense, out_shapes)
        result["float32"]["spconv_vs_dense64"] = _diffs(s32, dense, out_shapes)
    return result


def same_outputs(a: Sequence[Tensor], b: Sequence[Tensor]) -> tuple[bool, float]:
    """(bitwise equal, max abs difference) of two calls' output tensors (same order); differing shapes are unequal
    with an infinite difference."""
    if len(a) != len(b) or any(x.shape != y.shape for x, y in zip(a, b)):
        return False, float("inf")
    equal = all(torch.equal(x, y) for x, y in zip(a, b))
    diff = max((float((x.double() - y.double()).abs().max()) for x, y in zip(a, b) if x.numel()), default=0.0)
    return equal, diff
