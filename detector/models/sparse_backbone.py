"""Sparse PointPillars backbone + neck (the paper's Fig. 5b) and its ablations, up to the dense 384-channel map.

Input: a ``detector.sparse.SparseTensor`` of pillar features on the (ny, nx) pseudo-image grid (coords
``[b, iy, ix]``). Block i (channels 64/128/256, L = 3/5/5):

    SparseConv2d 2x2 stride 2 → BN → ReLU → L_i x (SubMConv2d 3x3 → BN → ReLU)

with BatchNorm over the active sites only (pooled over the batch) and no conv biases. The first SubM of each block
has ``first_subm_kernel`` (9 for Sparse+WideConv as the paper's text describes it); ``down_kernel=9`` makes the
down-conv 9x9 stride 2 instead (Sparse+WideConv as the released code builds it). Neck level i: a transposed conv
with kernel = stride = u_i (1/2/4) evaluated on the **block-1 active set**, BN, ReLU; the levels are concatenated and
scattered into one zero canvas (B, 384, ny/2, nx/2), so every inactive site is exactly zero and the active mask is the
block-1 set.

Ablations (``sparse_blocks``): 1 = Sparse1+Dense23, 2 = Sparse12+Dense3. The sparse blocks/levels run as above; the
last sparse block is densified and the remaining blocks are the dense SECOND blocks (3x3 stride-2 conv first, from
``detector.models.backbone.dense_block``) with dense ConvTranspose2d levels (``detector.models.neck.upsample_block``).
Their output is dense everywhere, so they return no active mask. Note the sparse blocks use a 2x2 stride-2 down-conv
where the dense backbone uses 3x3 stride 2: different architectures, as in the paper.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from detector.models.backbone import dense_block
from detector.models.neck import upsample_block
from detector.models.scatter import canvas_channels_last
from detector.sparse import (
    SparseBatchNorm,
    SparseConv2d,
    SparseConvTranspose2d,
    SparseReLU,
    SparseSequential,
    SparseTensor,
    SubMConv2d,
)
from detector.sparse.conv import init_weight_
from detector.sparse.indices import Downsample
from detector.sparse.phases import phase
from detector.sparse.tensor import scatter_to_dense
from detector.sparse.workspace import inference_workspace


def sparse_block(
    in_channels: int,
    out_channels: int,
    num_layers: int,
    *,
    first_subm_kernel: int = 3,
    down_kernel: int = 2,
    downsample: Downsample = "floor",
    indice_key: str = "subm",
    bn_eps: float = 1e-3,
    bn_momentum: float = 0.01,
) -> SparseSequential:
    """One sparse block: SparseConv2d(2x2, stride 2) → BN → ReLU, then ``num_layers`` x (SubMConv2d → BN → ReLU).

    SparseTensor on (H, W) → SparseTensor on (H/2, W/2) with sites ``unique(floor(c / 2))``; ``down_kernel=9``: a 9x9
    stride-2 down-conv (padding 4) instead, whose sites are every site with an input in its window. All SubM convs of
    the block share one neighbour table per kernel size through ``indice_key``.
    """
    layers: list[nn.Module] = [
        SparseConv2d(in_channels, out_channels, down_kernel, 2, downsample=downsample),
        SparseBatchNorm(out_channels, eps=bn_eps, momentum=bn_momentum),
        SparseReLU(),
    ]
    for j in range(num_layers):
        k = first_subm_kernel if j == 0 else 3
        layers += [
            SubMConv2d(out_channels, out_channels, k, indice_key=indice_key),
            SparseBatchNorm(out_channels, eps=bn_eps, momentum=bn_momentum),
            SparseReLU(),
        ]
    return SparseSequential(*layers)


class SparseUpsample(nn.Module):
    """Neck level on the block-1 set: SparseConvTranspose2d(kernel = stride = u) → BN → ReLU.

    ``forward(x, target)``: coarse SparseTensor, block-1 SparseTensor → SparseTensor on ``target``'s sites with
    ``out_channels`` features.
    """

    def __init__(
        self, in_channels: int, out_channels: int, stride: int, bn_eps: float = 1e-3, bn_momentum: float = 0.01
    ) -> None:
        super().__init__()
        self.deconv = SparseConvTranspose2d(in_channels, out_channels, stride, stride)
        self.norm = SparseBatchNorm(out_channels, eps=bn_eps, momentum=bn_momentum)
        self.act = SparseReLU()

    def forward(self, x: SparseTensor, target: SparseTensor) -> SparseTensor:
        return self.act(self.norm(self.deconv(x, target)))


def dense_active_mask(x: Tensor) -> Tensor:
    """``(B, C, H, W)`` map → ``(B, H, W)`` bool, True where any channel is non-zero.

    For the exact sparse head on a map that is zero off its active set: sites this marks False are all-zero, so the head
    gives exactly its bias there (an active site whose features all happen to be zero is marked False, which is still
    exact for the same reason).
    """
    return (x != 0).any(dim=1)


class SparseBackboneNeck(nn.Module):
    """Sparse backbone + neck: SparseTensor (B, C_in, ny, nx) → (dense map, active mask).

    Args:
        in_channels: pillar feature channels (64).
        layer_channels, layer_nums: per block (64/128/256, 3/5/5); every block down-samples by 2.
        out_channels, upsample_strides: per neck level (128/128/128, 1/2/4); ``upsample_strides[i]`` must be
            ``2**i`` (each level lands on the block-1 resolution).
        sparse_blocks: how many leading blocks (and neck levels) are sparse: 3 = Sparse PointPillars, 2 =
            Sparse12+Dense3, 1 = Sparse1+Dense23.
        first_subm_kernel: kernel of the first SubM conv of every sparse block (3; 9 = Sparse+WideConv as the paper's
            text describes it).
        down_kernel: kernel of every sparse block's stride-2 down-conv (2; 9 = Sparse+WideConv as the released code
            builds it: a 9x9 stride-2 down-conv, padding 4, with 3x3 SubMs after it).
        downsample: ``"floor"`` (paper) or ``"reference_quirk"`` (the released code's MinkowskiEngine output sites).
        bn_eps, bn_momentum: every BatchNorm (reference: 1e-3, 0.01).

    ``forward`` returns ``(B, sum(out_channels), ny/2, nx/2)`` and, for ``sparse_blocks == len(layer_channels)``,
    the ``(B, ny/2, nx/2)`` bool block-1 active set (the map is exactly zero elsewhere); ``None`` for the ablations,
    whose dense tail fills the whole map.
    """

    def __init__(
        self,
        in_channels: int = 64,
        layer_channels: Sequence[int] = (64, 128, 256),
        layer_nums: Sequence[int] = (3, 5, 5),
        out_channels: Sequence[int] = (128, 128, 128),
        upsample_strides: Sequence[int] = (1, 2, 4),
        sparse_blocks: int = 3,
        first_subm_kernel: int = 3,
        down_kernel: int = 2,
        downsample: Downsample = "floor",
        bn_eps: float = 1e-3,
        bn_momentum: float = 0.01,
    ) -> None:
        super().__init__()
        n = len(layer_channels)
        if not (len(layer_nums) == len(out_channels) == len(upsample_strides) == n):
            raise ValueError(
                "SparseBackboneNeck: layer_channels, layer_nums, out_channels, upsample_strides need equal lengths"
            )
        if list(upsample_strides) != [2**i for i in range(n)]:
            raise ValueError(
                f"SparseBackboneNeck: upsample_strides must be {[2**i for i in range(n)]} (every level lands on the "
                f"block-1 resolution), got {list(upsample_strides)}"
            )
        if not 1 <= sparse_blocks <= n:
            raise ValueError(f"SparseBackboneNeck: sparse_blocks must be in 1..{n}, got {sparse_blocks}")
        self.sparse_blocks = sparse_blocks
        self.out_channels = int(sum(out_channels))
        ins = [in_channels, *layer_channels[:-1]]
        self.blocks = nn.ModuleList(
            sparse_block(
                ins[i],
                layer_channels[i],
                layer_nums[i],
                first_subm_kernel=first_subm_kernel,
                down_kernel=down_kernel,
                downsample=downsample,
                indice_key=f"subm{i + 1}",
                bn_eps=bn_eps,
                bn_momentum=bn_momentum,
            )
            if i < sparse_blocks
            else dense_block(ins[i], layer_channels[i], layer_nums[i], 2)
            for i in range(n)
        )
        self.deblocks = nn.ModuleList(
            SparseUpsample(layer_channels[i], out_channels[i], upsample_strides[i], bn_eps, bn_momentum)
            if i < sparse_blocks
            else upsample_block(layer_channels[i], out_channels[i], upsample_strides[i])
            for i in range(n)
        )
        for m in self.modules():
            if isinstance(m, nn.modules.batchnorm._BatchNorm):
                # the dense tail comes from backbone.py / neck.py with the reference constants; honour ours
                m.eps, m.momentum = bn_eps, bn_momentum
            if isinstance(m, (SparseConv2d, SubMConv2d)):
                # the dense backbone's init (Kaiming normal, fan_out, ReLU gain); weights have the Conv2d layout, so
                # fan_out is the same number (drawn as for a contiguous weight; ours are stored channels-last)
                init_weight_(m.weight, lambda w: nn.init.kaiming_normal_(w, mode="fan_out", nonlinearity="relu"))

    @property
    def all_sparse(self) -> bool:
        """True when every block and neck level is sparse (Sparse PointPillars; False for the ablations)."""
        return self.sparse_blocks == len(self.blocks)

    def _sparse_part(self, x: SparseTensor) -> tuple[SparseTensor, Tensor, list[SparseTensor]]:
        """The sparse blocks and levels: (block-1 tensor, the levels' features concatenated on its sites, every
        sparse block's output)."""
        sparse_outs: list[SparseTensor] = []
        for block in self.blocks[: self.sparse_blocks]:
            x = block(x)
            sparse_outs.append(x)
        target = sparse_outs[0]
        levels = [deblock(s, target).features for deblock, s in zip(self.deblocks, sparse_outs)]
        # one scatter of the concatenated levels: the canvas is written once (it dominates the sparse model's time)
        ws = inference_workspace(target.workspace)
        with phase("scatter"):  # each site's levels written into its one row
            if len(levels) == 1:
                feats = levels[0]
            elif ws is None:
                feats = torch.cat(levels, dim=1)
            else:
                width = sum(lv.shape[1] for lv in levels)
                feats = torch.cat(levels, dim=1, out=ws.take(self, "levels", (target.num_active, width),
                                                              levels[0].dtype, levels[0].device))
        return target, feats, sparse_outs

    def neck_rows(self, x: SparseTensor) -> SparseTensor:
        """The all-sparse model's neck output before todense: a SparseTensor on the block-1 sites with the
        ``sum(out_channels)`` concatenated level features (the map :meth:`forward` returns is this, scattered into
        zeros). Training uses it to skip the canvas (see ``PointPillars.forward``)."""
        if not self.all_sparse:
            raise ValueError("neck_rows needs the all-sparse model (sparse_blocks == number of blocks)")
        target, feats, _ = self._sparse_part(x)
        return target.replace_feature(feats)

    def forward(self, x: SparseTensor) -> tuple[Tensor, Tensor | None]:
        """SparseTensor on (ny, nx) → ((B, 384, ny/2, nx/2) map, (B, ny/2, nx/2) bool active set or None).

        The map of the all-sparse model is in ``torch.channels_last`` memory format (``.contiguous()`` gives NCHW
        strides); the ablations' map has the layout of :func:`detector.models.scatter.canvas_channels_last`."""
        target, feats, sparse_outs = self._sparse_part(x)
        x = sparse_outs[-1]
        ws = inference_workspace(target.workspace)
        if self.all_sparse:
            # Channels-last canvas: each active site's 384 values are one contiguous row, so the scatter writes N
            # rows instead of 384 * N scattered floats, and the head reads rows too. The (B, 384, H, W) view has
            # torch.channels_last strides (measured on the Matterport map, 2 threads: todense 7.9 → 2.4 ms, dense
            # 1x1 head 48 → 20 ms, exact sparse head gather 3.6 → 0.9 ms at 1 thread; docs/sparse.md).
            # With a workspace (inference) the canvas is reused: only last frame's sites are reset (docs/sparse.md).
            hwc = scatter_to_dense(feats, target.keys(), target.spatial_shape, target.batch_size, channels_first=False,
                                   workspace=ws, owner=self)
            return hwc.permute(0, 3, 1, 2), target.active_mask()
        # the dense tail runs in the layout of the dense model's canvas (channels-last at inference, see
        # detector.models.scatter), so the head gets the same layout from every model
        cl = canvas_channels_last(feats.device.type)
        canvas = scatter_to_dense(feats, target.keys(), target.spatial_shape, target.batch_size, channels_first=not cl,
                                  workspace=ws, owner=self)
        # the last sparse block owns the canvas of its own output
        d = scatter_to_dense(x.features, x.keys(), x.spatial_shape, x.batch_size, channels_first=not cl,
                             workspace=ws, owner=self.blocks[self.sparse_blocks - 1])
        if cl:
            canvas, d = canvas.permute(0, 3, 1, 2), d.permute(0, 3, 1, 2)
        maps = [canvas]
        for block, deblock in zip(self.blocks[self.sparse_blocks :], self.deblocks[self.sparse_blocks :]):
            d = block(d)
            maps.append(deblock(d))
        return torch.cat(maps, dim=1), None
