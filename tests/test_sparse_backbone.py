"""SparseBackboneNeck equals the same network computed densely with the active masks applied after every layer."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from detector.models.sparse_backbone import SparseBackboneNeck, SparseUpsample, dense_active_mask
from detector.sparse import SparseBatchNorm, SparseConv2d, SparseTensor, SubMConv2d
from detector.sparse.synthetic import clustered_sites

TOL = 1e-9
SHAPE = (32, 24)
SMALL = dict(in_channels=4, layer_channels=(4, 6, 8), layer_nums=(1, 2, 1), out_channels=(3, 3, 3))


def make_input(seed: int = 0) -> SparseTensor:
    coords = clustered_sites(SHAPE, 0.12, batch_size=2, seed=seed)
    feats = torch.randn(coords.shape[0], 4, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    return SparseTensor(feats, coords, SHAPE, 2)


def randomise_norms(model: torch.nn.Module, seed: int) -> None:
    """Non-trivial BN parameters and running statistics, so that eval mode tests more than the identity."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
                n = m.num_features
                m.weight.copy_(0.5 + torch.rand(n, generator=g, dtype=torch.float64))
                m.bias.copy_(torch.randn(n, generator=g, dtype=torch.float64))
                m.running_mean.copy_(torch.randn(n, generator=g, dtype=torch.float64))
                m.running_var.copy_(0.5 + torch.rand(n, generator=g, dtype=torch.float64))


def masked_bn(d: torch.Tensor, mask: torch.Tensor, bn: SparseBatchNorm) -> torch.Tensor:
    """BatchNorm of a dense map whose statistics (training mode) come from the active sites only, then re-masked."""
    m = mask[:, None].to(d.dtype)
    if bn.training:
        n = m.sum()
        mean = (d * m).sum(dim=(0, 2, 3)) / n
        var = (((d - mean[None, :, None, None]) * m) ** 2).sum(dim=(0, 2, 3)) / n
    else:
        mean, var = bn.running_mean, bn.running_var
    y = (d - mean[None, :, None, None]) / torch.sqrt(var[None, :, None, None] + bn.eps)
    return (y * bn.weight[None, :, None, None] + bn.bias[None, :, None, None]) * m


def dense_reference(model: SparseBackboneNeck, x: SparseTensor) -> torch.Tensor:
    """The sparse network evaluated with dense torch ops on zero-filled maps, masking after every layer."""
    d, mask = x.dense(), x.active_mask()
    outs, masks = [], []
    for i, block in enumerate(model.blocks):
        if i >= model.sparse_blocks:
            d = block(d)  # the dense tail of an ablation
            outs.append(d)
            continue
        for layer in block:
            if isinstance(layer, SparseConv2d):
                d = F.conv2d(d, layer.weight, stride=2)
                m = mask[:, None].double()
                if layer.downsample == "floor":
                    mask = F.max_pool2d(m, 2)[:, 0] > 0  # floor(c / 2) of the active sites
                else:
                    # ceil(c / 2): output q is active iff an input sits at 2q - 1 or 2q (per axis)
                    mask = F.max_pool2d(F.pad(m, (1, 0, 1, 0)), 2)[:, 0, : d.shape[2], : d.shape[3]] > 0
                d = d * mask[:, None]
            elif isinstance(layer, SubMConv2d):
                d = F.conv2d(d, layer.weight, padding=layer.kernel_size // 2) * mask[:, None]
            elif isinstance(layer, SparseBatchNorm):
                d = masked_bn(d, mask, layer)
            else:
                d = F.relu(d)
        outs.append(d)
        masks.append(mask)
    levels = []
    for i, (deblock, o) in enumerate(zip(model.deblocks, outs)):
        if isinstance(deblock, SparseUpsample):
            u = F.conv_transpose2d(o, deblock.deconv.weight, stride=deblock.deconv.stride) * masks[0][:, None]
            levels.append(F.relu(masked_bn(u, masks[0], deblock.norm)))
        else:
            assert i >= model.sparse_blocks
            levels.append(deblock(o))
    return torch.cat(levels, dim=1)


@pytest.mark.parametrize("train", [False, True])
@pytest.mark.parametrize("first_subm_kernel", [3, 9])
def test_full_sparse_backbone_equals_masked_dense_chain(train: bool, first_subm_kernel: int) -> None:
    torch.manual_seed(0)
    model = SparseBackboneNeck(**SMALL, first_subm_kernel=first_subm_kernel).double()
    randomise_norms(model, 1)
    model.train(train)
    x = make_input()
    out, active = model(x)
    assert out.shape == (2, 9, SHAPE[0] // 2, SHAPE[1] // 2)
    assert out.is_contiguous(memory_format=torch.channels_last)  # rows of 9 channels per site (docs/sparse.md)
    ref = dense_reference(model, x)  # training mode: batch statistics over the active sites, as the sparse BN
    for level in range(3):
        sl = slice(3 * level, 3 * level + 3)
        torch.testing.assert_close(out[:, sl], ref[:, sl], atol=TOL, rtol=0)
    # exactly zero off the block-1 active set, and the mask helper recovers (a subset of) that set
    assert active is not None and active.shape == (2, SHAPE[0] // 2, SHAPE[1] // 2)
    assert bool((out[~active[:, None].expand_as(out)] == 0).all())
    assert bool((dense_active_mask(out) <= active).all())
    expected = F.max_pool2d(x.active_mask()[:, None].double(), 2)[:, 0] > 0
    assert torch.equal(active, expected)


def test_forward_backward_batch_two() -> None:
    torch.manual_seed(0)
    model = SparseBackboneNeck(**SMALL).double().train()
    x = make_input(seed=2)
    x = x.replace_feature(x.features.requires_grad_(True))
    out, _ = model(x)
    (out**2).sum().backward()
    assert x.features.grad is not None and bool(x.features.grad.abs().sum() > 0)
    for name, p in model.named_parameters():
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()), name
        assert bool(p.grad.abs().sum() > 0), name


@pytest.mark.parametrize("sparse_blocks", [1, 2])
def test_ablations_equal_sparse_head_then_dense_tail(sparse_blocks: int) -> None:
    torch.manual_seed(0)
    model = SparseBackboneNeck(**SMALL, sparse_blocks=sparse_blocks).double()
    randomise_norms(model, 2)
    model.eval()
    x = make_input(seed=3)
    out, active = model(x)
    assert active is None and out.shape == (2, 9, SHAPE[0] // 2, SHAPE[1] // 2)
    # the dense tail starts with a 3x3 stride-2 conv (the PointPillars block), the sparse blocks with 2x2
    assert model.blocks[sparse_blocks][0].kernel_size == (3, 3)
    assert model.blocks[0][0].kernel_size == 2
    torch.testing.assert_close(out, dense_reference(model, x), atol=TOL, rtol=0)
    model.train()
    out, _ = model(x)
    out.sum().backward()
    assert all(p.grad is not None for p in model.parameters())


def test_state_dict_shapes_match_dense_layers() -> None:
    model = SparseBackboneNeck()
    sd = model.state_dict()
    assert sd["blocks.0.0.weight"].shape == (64, 64, 2, 2)  # Conv2d layout (out, in, kh, kw)
    assert sd["blocks.0.3.weight"].shape == (64, 64, 3, 3)
    assert sd["deblocks.2.deconv.weight"].shape == (256, 128, 4, 4)  # ConvTranspose2d layout (in, out, kh, kw)
    wide = SparseBackboneNeck(first_subm_kernel=9).state_dict()
    assert wide["blocks.1.3.weight"].shape == (128, 128, 9, 9) and wide["blocks.1.6.weight"].shape == (128, 128, 3, 3)


def test_bad_arguments_raise() -> None:
    with pytest.raises(ValueError, match="upsample_strides"):
        SparseBackboneNeck(upsample_strides=(1, 2, 8))
    with pytest.raises(ValueError, match="sparse_blocks"):
        SparseBackboneNeck(sparse_blocks=0)


def test_reference_quirk_backbone_equals_masked_dense_chain() -> None:
    torch.manual_seed(0)
    model = SparseBackboneNeck(**SMALL, downsample="reference_quirk").double()
    randomise_norms(model, 3)
    model.eval()
    x = make_input(seed=4)
    # keep rounded-up sites inside the grid (the reference pads its grid for this); 32 x 24 then stays valid for
    # all three levels (rows < 24 → block-1 rows <= 12 → <= 6 → <= 3, all inside 16, 8, 4; likewise columns)
    keep = (x.coords[:, 1] < SHAPE[0] - 8) & (x.coords[:, 2] < SHAPE[1] - 8)
    x = SparseTensor(x.features[keep], x.coords[keep], SHAPE, 2)
    out, active = model(x)
    ref = dense_reference(model, x)
    torch.testing.assert_close(out, ref, atol=TOL, rtol=0)
    # the quirk drops inputs: some block-1 sites get no input, unlike floor semantics
    floor_active = F.max_pool2d(x.active_mask()[:, None].double(), 2)[:, 0] > 0
    assert active is not None and not torch.equal(active, floor_active)


def test_empty_batch_gives_zero_map() -> None:
    model = SparseBackboneNeck(**SMALL).double().train()
    x = SparseTensor(torch.zeros(0, 4, dtype=torch.float64), torch.zeros(0, 3, dtype=torch.int64), SHAPE, 2)
    out, active = model(x)
    assert out.shape == (2, 9, SHAPE[0] // 2, SHAPE[1] // 2) and not bool(out.any()) and not bool(active.any())
