"""Sparse ops equal their dense torch.nn twins on the active sites (float64, 1e-9), with gradients."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from detector.sparse import (
    SiteLookup,
    SparseBatchNorm,
    SparseConv2d,
    SparseConvTranspose2d,
    SparseReLU,
    SparseSequential,
    SparseTensor,
    SubMConv2d,
    subm_table,
)
from detector.sparse.indices import flat_keys
from detector.sparse.synthetic import clustered_sites, uniform_sites

TOL = 1e-9
SHAPE = (13, 11)  # odd on both axes: the last row/column has no full 2x2 window


def make_tensor(
    pattern: str, channels: int = 3, shape: tuple[int, int] = SHAPE, seed: int = 0, batch: int = 3
) -> SparseTensor:
    """Batch of `batch` items where item 1 is empty, plus the four corners of item 0 (border handling)."""
    if pattern == "clustered":
        coords = clustered_sites(shape, 0.2, batch_size=batch, seed=seed)
    else:
        coords = uniform_sites(shape, 0.3, batch_size=batch, seed=seed)
    h, w = shape
    corners = torch.tensor([[0, 0, 0], [0, 0, w - 1], [0, h - 1, 0], [0, h - 1, w - 1]])
    coords = torch.cat([coords[coords[:, 0] != 1], corners]).unique(dim=0)
    # shuffle rows: the ops must not rely on sorted input
    coords = coords[torch.randperm(coords.shape[0], generator=torch.Generator().manual_seed(seed))]
    feats = torch.randn(coords.shape[0], channels, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    return SparseTensor(feats, coords, shape, batch)


def at_sites(dense: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W) sampled at (N, 3) [b, y, x] → (N, C)."""
    return dense[coords[:, 0], :, coords[:, 1], coords[:, 2]]


@pytest.mark.parametrize("pattern", ["clustered", "uniform"])
@pytest.mark.parametrize("kernel_size", [1, 3, 5, 9])
@pytest.mark.parametrize("algorithm", ["gemm", "rulebook"])
def test_subm_equals_dense_conv(pattern: str, kernel_size: int, algorithm: str) -> None:
    x = make_tensor(pattern)
    conv = SubMConv2d(3, 4, kernel_size, bias=True, algorithm=algorithm).double()
    y = conv(x)
    ref = F.conv2d(x.dense(), conv.weight, conv.bias, padding=kernel_size // 2)
    assert torch.equal(y.coords, x.coords)
    torch.testing.assert_close(y.features, at_sites(ref, x.coords), atol=TOL, rtol=0)
    # .dense() of the result is the dense op masked to the active sites
    torch.testing.assert_close(y.dense(), ref * x.active_mask()[:, None], atol=TOL, rtol=0)


def test_subm_tables_agree_between_lookup_modes() -> None:
    x = make_tensor("clustered", seed=3)
    keys = flat_keys(x.coords, x.spatial_shape)
    grid = SiteLookup(keys, x.spatial_shape, x.batch_size, mode="grid")
    srt = SiteLookup(keys, x.spatial_shape, x.batch_size, mode="sorted")
    for k in (3, 5):
        a = subm_table(x.coords, x.spatial_shape, grid, k).table
        b = subm_table(x.coords, x.spatial_shape, srt, k).table
        assert torch.equal(a, b)
        assert int((a >= 0).sum()) > x.num_active  # there are real neighbours, so the comparison means something


def test_indice_key_shares_the_table_per_kernel_size() -> None:
    x = make_tensor("clustered")
    a = SubMConv2d(3, 3, 3, indice_key="b1").double()
    b = SubMConv2d(3, 3, 3, indice_key="b1").double()
    wide = SubMConv2d(3, 3, 9, indice_key="b1").double()
    y = b(a(x))
    wide(y)
    assert a.table(x) is b.table(y)
    assert wide.table(y) is not a.table(x)
    assert wide.table(y).table.shape[1] == 81


@pytest.mark.parametrize("pattern", ["clustered", "uniform"])
@pytest.mark.parametrize("stride", [2, 4])
def test_down_conv_equals_strided_dense_conv(pattern: str, stride: int) -> None:
    x = make_tensor(pattern, seed=1)
    conv = SparseConv2d(3, 5, stride, stride, bias=True).double()
    y = conv(x)
    ref = F.conv2d(x.dense(), conv.weight, conv.bias, stride=stride)
    h, w = SHAPE
    assert y.spatial_shape == (h // stride, w // stride) == tuple(ref.shape[2:])
    c = x.coords
    inside = (c[:, 1] // stride < h // stride) & (c[:, 2] // stride < w // stride)
    parents = torch.stack([c[:, 0], c[:, 1] // stride, c[:, 2] // stride], 1)[inside]
    assert torch.equal(y.coords, parents.unique(dim=0))  # output set = unique(floor(c / s)), sorted
    torch.testing.assert_close(y.features, at_sites(ref, y.coords), atol=TOL, rtol=0)
    # at inactive outputs the dense conv sees only zeros: only the bias is left there
    torch.testing.assert_close(
        y.dense() + conv.bias[None, :, None, None] * (~y.active_mask())[:, None], ref, atol=TOL, rtol=0
    )


@pytest.mark.parametrize("pattern", ["clustered", "uniform"])
@pytest.mark.parametrize("kernel_size", [3, 9])
def test_wide_down_conv_equals_padded_strided_dense_conv(pattern: str, kernel_size: int) -> None:
    """The released code's Sparse+WideConv down-conv: k x k, stride 2, padding k // 2, generative output set."""
    x = make_tensor(pattern, shape=(14, 12), seed=3)
    conv = SparseConv2d(3, 5, kernel_size, 2, bias=True).double()
    y = conv(x)
    p = kernel_size // 2
    ref = F.conv2d(x.dense(), conv.weight, conv.bias, stride=2, padding=p)
    assert y.spatial_shape == (7, 6) == tuple(ref.shape[2:])
    # output set: every site whose window holds an input = where an all-ones conv of the occupancy is positive
    occupancy = x.active_mask()[:, None].double()
    reach = F.conv2d(occupancy, torch.ones(1, 1, kernel_size, kernel_size, dtype=torch.float64), stride=2, padding=p)
    assert torch.equal(y.active_mask(), reach[:, 0] > 0) and y.num_active > x.num_active // 4
    keys = flat_keys(y.coords, y.spatial_shape)
    assert torch.equal(keys, keys.sort().values)  # rows sorted by site
    torch.testing.assert_close(y.features, at_sites(ref, y.coords), atol=TOL, rtol=0)
    torch.testing.assert_close(
        y.dense() + conv.bias[None, :, None, None] * (~y.active_mask())[:, None], ref, atol=TOL, rtol=0
    )
    with pytest.raises(ValueError, match="kernel_size == stride only"):
        SparseConv2d(3, 5, kernel_size, 2, downsample="reference_quirk")
    with pytest.raises(ValueError, match="odd kernel_size > stride"):
        SparseConv2d(3, 5, 4, 2)


def test_gradcheck_wide_down_conv() -> None:
    x = _tiny("clustered", 2, (6, 4), 1)
    down = SparseConv2d(2, 2, 5, 2, bias=True).double()

    def fn(f: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        return torch.func.functional_call(down, {"weight": w, "bias": down.bias}, (x.replace_feature(f),)).features

    assert torch.autograd.gradcheck(fn, (x.features, down.weight.detach().clone().requires_grad_(True)))


@pytest.mark.parametrize("stride", [1, 2, 4])
def test_transposed_conv_on_target_set_equals_dense(stride: int) -> None:
    coarse = make_tensor("clustered", channels=4, shape=(5, 4), seed=2)
    target = make_tensor("uniform", channels=1, shape=(5 * stride, 4 * stride), seed=5)
    conv = SparseConvTranspose2d(4, 3, stride, stride, bias=True).double()
    y = conv(coarse, target)
    ref = F.conv_transpose2d(coarse.dense(), conv.weight, conv.bias, stride=stride)
    assert torch.equal(y.coords, target.coords) and y.spatial_shape == target.spatial_shape
    torch.testing.assert_close(y.features, at_sites(ref, target.coords), atol=TOL, rtol=0)
    if stride > 1:
        # the target set includes sites whose coarse parent is inactive; they get exactly the bias
        parent_active = coarse.active_mask()[
            target.coords[:, 0], target.coords[:, 1] // stride, target.coords[:, 2] // stride
        ]
        assert bool((~parent_active).any())
    same = conv if stride == 1 else SparseConvTranspose2d(4, 3, 1, 1).double()
    torch.testing.assert_close(
        same(coarse, coarse).features,
        at_sites(F.conv_transpose2d(coarse.dense(), same.weight, same.bias), coarse.coords),
        atol=TOL,
        rtol=0,
    )


def test_transposed_conv_with_no_active_parent_or_no_target_gives_bias() -> None:
    coarse = make_tensor("clustered", channels=4, shape=(5, 4), seed=2)
    conv = SparseConvTranspose2d(4, 3, 4, 4, bias=True).double()
    # targets whose coarse parents (the top-left 2 x 2 of item 1, which is empty) are all inactive
    far = torch.tensor([[1, 0, 0], [1, 3, 5], [1, 7, 2]])
    y = conv(coarse, SparseTensor(torch.zeros(3, 1, dtype=torch.float64), far, (20, 16), coarse.batch_size))
    torch.testing.assert_close(y.features, conv.bias.expand(3, 3), atol=0, rtol=0)
    none = SparseTensor(torch.zeros(0, 1, dtype=torch.float64), torch.zeros(0, 3, dtype=torch.int64), (20, 16),
                        coarse.batch_size)
    assert conv(coarse, none).features.shape == (0, 3)


def test_weights_copy_from_dense_layers() -> None:
    """A dense layer's state_dict loads into its sparse twin (same keys and shapes, strict), and the twin then computes
    the dense layer's output at its active sites."""
    x = make_tensor("clustered", seed=4)
    target = make_tensor("uniform", channels=1, shape=(4 * SHAPE[0], 4 * SHAPE[1]), seed=6)
    torch.manual_seed(0)
    pairs = [
        (SubMConv2d(3, 4, 5, bias=True), nn.Conv2d(3, 4, 5, padding=2), lambda m: m(x), x.coords),
        (SparseConv2d(3, 4, bias=True), nn.Conv2d(3, 4, 2, 2), lambda m: m(x), None),
        (SparseConvTranspose2d(3, 4, 4, 4, bias=True), nn.ConvTranspose2d(3, 4, 4, 4), lambda m: m(x, target),
         target.coords),
    ]
    for sparse, dense, call, sites in pairs:
        sparse, dense = sparse.double(), dense.double()
        sparse.load_state_dict(dense.state_dict())  # strict: the same parameter names and shapes
        y = call(sparse)
        if sites is not None:
            assert torch.equal(y.coords, sites)
        torch.testing.assert_close(y.features, at_sites(dense(x.dense()), y.coords), atol=TOL, rtol=0)
    assert SubMConv2d(3, 4, 3).weight.shape == nn.Conv2d(3, 4, 3).weight.shape  # the reference's bias-free layers
    SubMConv2d(3, 4, 3).load_state_dict(nn.Conv2d(3, 4, 3, bias=False).state_dict())


def _tiny(pattern: str, channels: int, shape: tuple[int, int], seed: int) -> SparseTensor:
    x = make_tensor(pattern, channels=channels, shape=shape, seed=seed, batch=2)
    return x.replace_feature(x.features.clone().requires_grad_(True))


@pytest.mark.parametrize("algorithm", ["gemm", "rulebook"])
def test_gradcheck_subm(algorithm: str) -> None:
    from detector.sparse import subm_conv2d

    x = _tiny("clustered", 2, (5, 4), 0)
    table = subm_table(x.coords, x.spatial_shape, x.lookup(), 3)
    w = torch.randn(2, 2, 3, 3, dtype=torch.float64, requires_grad=True)
    b = torch.randn(2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda f, w, b: subm_conv2d(f, table, w, b, algorithm), (x.features, w, b))


def test_gradcheck_down_and_transposed() -> None:
    x = _tiny("clustered", 2, (6, 4), 1)
    down = SparseConv2d(2, 2, bias=True).double()
    up = SparseConvTranspose2d(2, 2, 2, 2, bias=True).double()

    def down_fn(f: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        return torch.func.functional_call(down, {"weight": w, "bias": down.bias}, (x.replace_feature(f),)).features

    def up_fn(f: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        coarse = down(x)
        c = coarse.replace_feature(f)
        return torch.func.functional_call(up, {"weight": w, "bias": up.bias}, (c, x)).features

    assert torch.autograd.gradcheck(down_fn, (x.features, down.weight.detach().clone().requires_grad_(True)))
    m = down(x).num_active
    f = torch.randn(m, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(up_fn, (f, up.weight.detach().clone().requires_grad_(True)))


def test_reference_quirk_test_vector() -> None:
    """Section 2.1 of the reference note (all-ones kernel, coordinates in input units, verified against ME 0.5.4)."""
    pts = torch.tensor([[4, 4], [7, 7], [10, 11], [13, 12], [20, 21], [21, 21]])
    feats = torch.tensor([1.0, 10.0, 100.0, 1e3, 1e4, 1e5], dtype=torch.float64)[:, None]
    x = SparseTensor(feats, torch.cat([torch.zeros(6, 1, dtype=torch.int64), pts], 1), (32, 32), 1)
    expected = {
        "floor": {(4, 4): 1.0, (6, 6): 10.0, (10, 10): 100.0, (12, 12): 1000.0, (20, 20): 110000.0},
        "reference_quirk": {(4, 4): 1.0, (8, 8): 0.0, (10, 12): 0.0, (14, 12): 0.0, (20, 22): 0.0, (22, 22): 0.0},
    }
    for mode, table in expected.items():
        conv = SparseConv2d(1, 1, downsample=mode).double()  # type: ignore[arg-type]
        with torch.no_grad():
            conv.weight.fill_(1.0)
        y = conv(x)
        got = {(2 * int(c[1]), 2 * int(c[2])): float(f) for c, f in zip(y.coords, y.features.detach()[:, 0])}
        assert got == table, mode


def test_reference_quirk_past_the_grid_raises() -> None:
    x = SparseTensor(torch.ones(1, 1), torch.tensor([[0, 7, 2]]), (8, 8), 1)
    SparseConv2d(1, 1)(x)  # floor is fine
    with pytest.raises(ValueError, match="pad the input grid"):
        SparseConv2d(1, 1, downsample="reference_quirk")(x)


def test_batchnorm_on_active_rows_equals_batchnorm1d() -> None:
    x = make_tensor("clustered", channels=4, seed=4)
    bn = SparseBatchNorm(4).double()
    ref = nn.BatchNorm1d(4, eps=1e-3, momentum=0.01).double()
    with torch.no_grad():
        for m in (bn, ref):
            m.weight.copy_(torch.linspace(0.5, 2.0, 4))
            m.bias.copy_(torch.linspace(-1.0, 1.0, 4))
    y = bn(x)
    torch.testing.assert_close(y.features, ref(x.features), atol=TOL, rtol=0)
    torch.testing.assert_close(bn.running_mean, ref.running_mean, atol=TOL, rtol=0)
    torch.testing.assert_close(bn.running_var, ref.running_var, atol=TOL, rtol=0)
    # inactive sites stay exactly zero after BN + ReLU
    d = SparseReLU()(y).dense()
    assert bool((d[~x.active_mask()[:, None].expand_as(d)] == 0).all())
    # the buffers are BatchNorm2d's, so a dense model's BN loads directly
    bn.load_state_dict(nn.BatchNorm2d(4).state_dict())
    bn.eval()
    dense_bn = nn.BatchNorm2d(4, eps=1e-3).double().eval()
    torch.testing.assert_close(bn(x).features, at_sites(dense_bn(x.dense()), x.coords), atol=TOL, rtol=0)


def test_batchnorm_with_no_active_site_keeps_running_stats() -> None:
    bn = SparseBatchNorm(2)
    empty = SparseTensor(torch.zeros(0, 2), torch.zeros(0, 3, dtype=torch.int64), (4, 4), 2)
    assert bn(empty).features.shape == (0, 2)
    assert torch.equal(bn.running_mean, torch.zeros(2)) and torch.equal(bn.running_var, torch.ones(2))


def test_sequential_feeds_plain_layers_features() -> None:
    x = make_tensor("uniform", channels=3)
    lin = nn.Linear(3, 2).double()
    seq = SparseSequential(SubMConv2d(3, 3, 3, indice_key="a").double(), SparseReLU(), lin)
    y = seq(x)
    assert torch.equal(y.coords, x.coords) and y.features.shape == (x.num_active, 2)
    assert ("subm", "a", 3) in y.cache  # the table is shared with every tensor on these sites


def test_dense_roundtrip_and_layouts() -> None:
    x = make_tensor("clustered", channels=3, seed=6)
    d = x.dense()
    assert d.shape == (3, 3, *SHAPE) and d.is_contiguous()
    assert torch.equal(x.dense(channels_first=False), d.permute(0, 2, 3, 1))
    back = SparseTensor.from_dense(d, x.active_mask())
    assert torch.equal(back.dense(), d)
    assert int(back.active_mask()[1].sum()) == 0  # the empty batch item stays empty
