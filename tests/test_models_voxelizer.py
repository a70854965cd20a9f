"""detector.models.voxelizer and pillar_net: caps and order against a slow reference, decorations by hand.

(Comparisons use numpy.testing: the first torch.testing.assert_close call imports ~10 s of CPU time.)"""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import torch

from detector.models.pillar_net import PillarFeatureNet
from detector.models.voxelizer import voxelize, voxelize_torch
from mpchair.geometry import pillar_coords

ROOT = Path(__file__).resolve().parents[1]
RANGE = (0.0, -1.0, -1.0, 2.0, 1.0, 1.0)
VOXEL = (0.5, 0.5, 2.0)  # a 4 x 4 grid


def slow_voxelize(points: np.ndarray, pc_range, voxel, max_points: int, max_pillars: int):
    """Textbook loop: walk points in input order; pillars numbered by first occurrence; caps by arrival."""
    order: list[tuple[int, int]] = []
    members: dict[tuple[int, int], list[int]] = {}
    for i, p in enumerate(points):
        if not all(pc_range[k] <= p[k] < pc_range[k + 3] for k in range(3)):
            continue
        key = (math.floor((p[1] - pc_range[1]) / voxel[1]), math.floor((p[0] - pc_range[0]) / voxel[0]))
        if key not in members:
            if len(order) == max_pillars:
                continue
            members[key] = []
            order.append(key)
        if len(members[key]) < max_points:
            members[key].append(i)
    return order, members


def test_voxelizer_matches_slow_reference_with_caps_hit() -> None:
    rng = np.random.default_rng(3)
    # Many points on a 4 x 4 grid plus some outside the range: both caps are hit.
    pts = rng.uniform([-0.5, -1.2, -1.2], [2.5, 1.2, 1.2], size=(400, 3)).astype(np.float32)
    ref_order, ref_members = slow_voxelize(pts, RANGE, VOXEL, max_points=5, max_pillars=9)
    v = voxelize(
        [torch.from_numpy(pts)],
        point_cloud_range=RANGE,
        voxel_size=VOXEL,
        output_shape=(4, 4),
        max_points=5,
        max_pillars=9,
    )
    assert len(ref_order) == 9 and v.pillars.shape == (9, 5, 3)
    assert v.coords[:, 0].tolist() == [0] * 9
    assert [tuple(c) for c in v.coords[:, 1:].tolist()] == ref_order
    for p, key in enumerate(ref_order):
        idx = ref_members[key]
        assert int(v.num_points[p]) == len(idx)
        np.testing.assert_array_equal(v.pillars[p, : len(idx)].numpy(), pts[idx])
        assert float(v.pillars[p, len(idx) :].abs().sum()) == 0.0
    # Deterministic: a second call is identical.
    v2 = voxelize(
        [torch.from_numpy(pts)],
        point_cloud_range=RANGE,
        voxel_size=VOXEL,
        output_shape=(4, 4),
        max_points=5,
        max_pillars=9,
    )
    assert all(torch.equal(a, b) for a, b in zip(v[:3], v2[:3]))


def test_voxelizer_batch_hand_case_and_canvas_drop() -> None:
    a = torch.tensor([[0.1, 0.1, 0.0], [1.9, -0.9, 0.0], [0.2, 0.2, 0.5], [2.0, 0.0, 0.0]])  # last: x == max → out
    b = torch.tensor([[1.2, 0.7, 0.0, 0.3]])[:, :3]
    v = voxelize([a, b], point_cloud_range=RANGE, voxel_size=VOXEL, output_shape=(4, 4), max_points=4, max_pillars=10)
    # a: (0.1, 0.1) → iy 2, ix 0 (first), (1.9, -0.9) → iy 0, ix 3; b: (1.2, 0.7) → iy 3, ix 2.
    assert v.coords.tolist() == [[0, 2, 0], [0, 0, 3], [1, 3, 2]]
    assert v.num_points.tolist() == [2, 1, 1] and v.batch_size == 2
    # A canvas smaller than the grid drops the pillars outside it (here column 3).
    v = voxelize([a], point_cloud_range=RANGE, voxel_size=VOXEL, output_shape=(4, 3), max_points=4, max_pillars=10)
    assert v.coords.tolist() == [[0, 2, 0]]
    # An empty sample yields no pillars but keeps the batch size.
    v = voxelize(
        [torch.zeros((0, 3))],
        point_cloud_range=RANGE,
        voxel_size=VOXEL,
        output_shape=(4, 4),
        max_points=4,
        max_pillars=10,
    )
    assert v.pillars.shape == (0, 4, 3) and v.batch_size == 1


def test_pfn_decorations_by_hand() -> None:
    net = PillarFeatureNet(in_channels=4, out_channels=8, voxel_size=VOXEL, point_cloud_range=RANGE)
    pillars = torch.zeros(1, 3, 4)
    pillars[0, 0] = torch.tensor([0.6, 0.2, 0.1, 0.5])
    pillars[0, 1] = torch.tensor([0.8, 0.4, 0.3, 0.9])
    coords = torch.tensor([[0, 2, 1]])  # iy 2, ix 1 → centre x = 1*0.5 + 0.25 + 0 = 0.75, y = 2*0.5 + 0.25 - 1 = 0.25
    d = net.decorate(pillars, torch.tensor([2]), coords)
    assert d.shape == (1, 3, 9)
    expected = torch.tensor(
        [
            [0.6, 0.2, 0.1, 0.5, -0.1, -0.1, -0.1, -0.15, -0.05],
            [0.8, 0.4, 0.3, 0.9, 0.1, 0.1, 0.1, 0.05, 0.15],
            [0.0] * 9,  # padded slot zeroed after decoration
        ]
    )
    np.testing.assert_allclose(d[0].numpy(), expected.numpy(), atol=1e-6, rtol=0)
    assert PillarFeatureNet(in_channels=3, out_channels=8, voxel_size=VOXEL, point_cloud_range=RANGE).num_features == 8


def test_pfn_forward_equals_reference_layout() -> None:
    torch.manual_seed(0)
    net = PillarFeatureNet(in_channels=3, out_channels=16, voxel_size=VOXEL, point_cloud_range=RANGE).train()
    ref = copy.deepcopy(net)
    pillars = torch.randn(7, 4, 3)
    num = torch.tensor([1, 2, 3, 4, 4, 2, 1])
    pillars[torch.arange(4)[None, :] >= num[:, None]] = 0
    coords = torch.stack([torch.zeros(7, dtype=torch.int64), torch.arange(7) % 4, torch.arange(7) // 4], dim=1)
    out = net(pillars, num, coords)
    # Reference layout: BN1d on the permuted (P, C, T) tensor, ReLU, max over slots (padded slots included).
    x = ref.linear(ref.decorate(pillars, num, coords))
    x = torch.relu(ref.norm(x.permute(0, 2, 1)).permute(0, 2, 1)).max(dim=1).values
    np.testing.assert_allclose(out.detach().numpy(), x.detach().numpy(), atol=1e-5, rtol=1e-5)
    np.testing.assert_allclose(net.norm.running_mean.numpy(), ref.norm.running_mean.numpy(), atol=1e-6)
    assert net.norm.eps == 1e-3 and net.norm.momentum == 0.01


# --- the compiled voxelizer against the vectorised-torch form (the one before it) ---------------------------------
KW = dict(point_cloud_range=RANGE, voxel_size=VOXEL, output_shape=(4, 4))


def _assert_same_voxels(a, b) -> None:
    assert a.batch_size == b.batch_size
    for x, y in zip(a[:3], b[:3]):
        assert x.dtype == y.dtype and x.shape == y.shape
        assert np.array_equal(x.numpy(), y.numpy())  # bit for bit (no NaN can reach a pillar)


def _edge_cloud(rng: np.random.Generator, n: int, c: int) -> np.ndarray:
    """Random points around RANGE with the hard cases mixed in: outside on every side, exactly on the lower bounds,
    exactly on and just below the upper bounds (the held-at-n-1 rule), on cell borders, NaN / inf, duplicates."""
    lo, hi = np.array(RANGE[:3]), np.array(RANGE[3:])
    pts = rng.uniform(lo - 0.3, hi + 0.3, size=(n, 3))
    k = n // 8
    pts[:k, 0] = rng.choice([lo[0], hi[0], np.nextafter(np.float32(hi[0]), np.float32(0)), 0.5, 1.0, 1.5], k)
    pts[k:2 * k, 1] = rng.choice([lo[1], hi[1], np.nextafter(np.float32(hi[1]), np.float32(0)), -0.5, 0.0], k)
    pts[2 * k:3 * k, 2] = rng.choice([lo[2], hi[2], np.nextafter(np.float32(hi[2]), np.float32(0))], k)
    pts[3 * k, 0], pts[3 * k + 1, 1], pts[3 * k + 2, 2] = np.nan, np.inf, -np.inf
    pts[-k:] = pts[rng.integers(0, n - k, k)]  # duplicates of earlier points
    extra = rng.uniform(0, 1, size=(n, c - 3))
    return np.concatenate([pts, extra], axis=1)


def test_compiled_voxelizer_equals_torch_form_on_random_and_edge_clouds() -> None:
    rng = np.random.default_rng(11)
    for trial in range(12):
        c = 3 + trial % 2
        dtype = np.float32 if trial < 10 else np.float64
        pts = torch.from_numpy(_edge_cloud(rng, int(rng.integers(50, 600)), c).astype(dtype))
        for max_points, max_pillars in ((32, 100), (3, 100), (1, 5), (4, 1)):
            caps = dict(max_points=max_points, max_pillars=max_pillars)
            _assert_same_voxels(voxelize([pts], **KW, **caps), voxelize_torch([pts], **KW, **caps))
    # a batch: a full sample, an empty one, one with every point outside the range, a non-contiguous view
    wide = torch.from_numpy(_edge_cloud(rng, 300, 4).astype(np.float32))
    batch = [wide[:, :3], torch.zeros((0, 3)), torch.full((5, 3), 9.0), torch.from_numpy(_edge_cloud(rng, 200, 3))
             .float()]
    assert not batch[0].is_contiguous()
    for shape in ((4, 4), (4, 3), (3, 4), (6, 8)):  # canvas equal to, smaller than (drops) and larger than the grid
        kw = dict(KW, output_shape=shape)
        got = voxelize(batch, **kw, max_points=5, max_pillars=9)
        _assert_same_voxels(got, voxelize_torch(batch, **kw, max_points=5, max_pillars=9))
        assert got.batch_size == 4 and set(got.coords[:, 0].tolist()) <= {0, 3}
    # empty and all-outside clouds alone
    for pts in (torch.zeros((0, 4)), torch.full((7, 4), -5.0)):
        got = voxelize([pts], **KW, max_points=4, max_pillars=10)
        _assert_same_voxels(got, voxelize_torch([pts], **KW, max_points=4, max_pillars=10))
        assert got.pillars.shape == (0, 4, 4) and got.coords.shape == (0, 3)


def test_compiled_voxelizer_keeps_the_indexing_rule_at_cell_borders() -> None:
    """Points on every cell border and just below each upper bound index as mpchair.geometry.pillar_coords says
    (a real 250 x 380 grid of 5 cm cells, where floor((p - min) / v) in float64 is the rule)."""
    rng_, vox = (0.0, -19.0, -2.0, 12.5, 0.0, 2.0), (0.05, 0.05, 4.0)
    xs = np.concatenate([np.arange(0, 251) * 0.05, np.nextafter(np.arange(1, 251) * 0.05, 0)])
    ys = np.concatenate([-19.0 + np.arange(0, 381) * 0.05, np.nextafter(-19.0 + np.arange(1, 381) * 0.05, -20)])
    pts = np.stack([np.resize(xs, 2000), np.resize(ys, 2000)[::-1], np.zeros(2000)], axis=1).astype(np.float32)
    kw = dict(point_cloud_range=rng_, voxel_size=vox, output_shape=(384, 256), max_points=64, max_pillars=5000)
    got = voxelize([torch.from_numpy(pts)], **kw)
    _assert_same_voxels(got, voxelize_torch([torch.from_numpy(pts)], **kw))
    cells, keep = pillar_coords(pts.astype(np.float64), rng_, vox)
    assert int(got.num_points.sum()) == int(keep.sum()) > 1500
    assert {tuple(c) for c in got.coords[:, 1:].tolist()} == {tuple(c) for c in cells.tolist()}


def test_compiled_voxelizer_is_deterministic_and_leaves_the_points_alone() -> None:
    pts = torch.from_numpy(_edge_cloud(np.random.default_rng(5), 500, 4).astype(np.float32))
    before = pts.clone()
    a = voxelize([pts], **KW, max_points=3, max_pillars=8)
    b = voxelize([pts], **KW, max_points=3, max_pillars=8)
    assert all(x.numpy().tobytes() == y.numpy().tobytes() for x, y in zip(a[:3], b[:3]))
    assert torch.equal(pts.nan_to_num(), before.nan_to_num())


# --- the fused eval-mode pillar net against the torch layers ------------------------------------------------------
#: fp32 rounding: the fused kernel computes in the order of torch's CPU kernels and is bitwise equal where they
#: accumulate as measured (MKL's FMA GEMM, torch.sum's four partial sums); elsewhere it may differ by rounding only.
PFN_ATOL = PFN_RTOL = 1e-5


def _trained_like_pfn(in_channels: int, seed: int) -> PillarFeatureNet:
    """A PillarFeatureNet with random weights and random BN statistics (some channels' ReLU mostly off), eval mode."""
    torch.manual_seed(seed)
    net = PillarFeatureNet(in_channels=in_channels, out_channels=64, voxel_size=VOXEL, point_cloud_range=RANGE)
    with torch.no_grad():
        net.norm.running_mean.uniform_(-1, 1)
        net.norm.running_var.uniform_(0.05, 3)
        net.norm.weight.uniform_(0.5, 2)
        net.norm.bias.uniform_(-2, 1)
    return net.eval()


def test_fused_pillar_net_equals_torch_layers_in_eval() -> None:
    rng = np.random.default_rng(21)
    for trial, (c, t) in enumerate([(3, 32), (4, 32), (3, 5), (4, 7), (3, 64), (4, 130), (3, 1)]):
        net = _trained_like_pfn(c, trial)
        # a blob on a 10 x 10 grid of 0.2 m cells: full pillars in its middle, a few points per pillar at its rim
        xyz = rng.normal([1.0, 0.0, 0.0], [0.35, 0.3, 0.4], size=(40 * t, 3))
        pts = torch.from_numpy(np.concatenate([xyz, rng.uniform(0, 1, (40 * t, c - 3))], axis=1).astype(np.float32))
        v = voxelize([pts], point_cloud_range=RANGE, voxel_size=(0.2, 0.2, 2.0), output_shape=(10, 10), max_points=t,
                     max_pillars=100)
        assert int(v.num_points.max()) == t and (t == 1 or int(v.num_points.min()) < t)  # full and padded pillars
        with torch.no_grad():
            assert net.fused_applies(v.pillars)
            fused = net(v.pillars, v.num_points, v.coords)
            ref = net.forward_torch(v.pillars, v.num_points, v.coords)
            exact = net.double().forward_torch(v.pillars.double(), v.num_points, v.coords)
        net.float()
        assert fused.shape == (v.pillars.shape[0], 64) and v.pillars.shape[0] > 15 and fused.dtype == torch.float32
        assert float((fused == 0).float().mean()) > 0.05 and float((fused > 0).float().mean()) > 0.3
        np.testing.assert_allclose(fused.numpy(), ref.numpy(), atol=PFN_ATOL, rtol=PFN_RTOL)
        # both fp32 forms are the float64 result to fp32 rounding
        np.testing.assert_allclose(fused.numpy(), exact.numpy(), atol=PFN_ATOL, rtol=PFN_RTOL)
        with torch.no_grad():  # deterministic: the same bytes again
            assert net(v.pillars, v.num_points, v.coords).numpy().tobytes() == fused.numpy().tobytes()


def test_fused_pillar_net_edge_cases() -> None:
    net = _trained_like_pfn(4, 3)
    coords = torch.tensor([[0, 1, 2], [0, 3, 0], [0, 0, 3]])
    pillars = torch.zeros(3, 4, 4)
    pillars[0, :4] = torch.tensor([[0.1, 0.2, 0.3, 0.5]] * 4)  # a full pillar of duplicates
    pillars[1, 0] = torch.tensor([1.9, 0.9, -0.9, 0.0])  # one point
    pillars[2, :2] = torch.tensor([[1.6, -0.6, 0.1, float("nan")], [1.7, -0.7, 0.2, 0.4]])  # NaN reflectance
    num = torch.tensor([4, 1, 2])
    with torch.no_grad():
        fused = net(pillars, num, coords)
        ref = net.forward_torch(pillars, num, coords)
        assert net(pillars[:0], num[:0], coords[:0]).shape == (0, 64)
    assert torch.isnan(ref[2]).all() and torch.isnan(fused[2]).all()  # NaN propagates through the max, as in torch
    np.testing.assert_allclose(fused[:2].numpy(), ref[:2].numpy(), atol=PFN_ATOL, rtol=PFN_RTOL)
    # a pillar whose slots are all real takes no padded value: with every pre-activation negative its output is 0
    with torch.no_grad():
        net.norm.bias.fill_(-50.0)
        full = net(pillars[:1], num[:1], coords[:1])
    assert float(full.abs().max()) == 0.0
    assert float(net(pillars[1:2], num[1:2], coords[1:2]).detach().abs().max()) == 0.0  # relu(beta) = 0 too


def test_pillar_net_takes_the_fused_path_only_for_fp32_cpu_inference_and_trains_on_real_points() -> None:
    net = _trained_like_pfn(3, 1)
    pillars = torch.randn(6, 4, 3)
    num = torch.tensor([1, 2, 3, 4, 4, 2])
    pillars[torch.arange(4)[None, :] >= num[:, None]] = 0
    coords = torch.stack([torch.zeros(6, dtype=torch.int64), torch.arange(6) % 4, torch.arange(6) // 4], dim=1)
    with torch.no_grad():
        assert net.fused_applies(pillars)
        assert not net.fused_applies(pillars.double())
        with torch.autocast("cpu", dtype=torch.bfloat16):
            assert not net.fused_applies(pillars)
    assert not net.fused_applies(pillars)  # eval with autograd on
    # training: the real-points form (the torch layers' values, test above), differentiable through Linear, BN
    # (batch statistics), ReLU and the max
    net.train()
    with torch.no_grad():
        assert not net.fused_applies(pillars) and net.compact_applies()
    out = net(pillars, num, coords)
    assert out.grad_fn is not None
    out.square().sum().backward()
    assert float(net.linear.weight.grad.abs().sum()) > 0 and float(net.norm.weight.grad.abs().sum()) > 0
    assert int(net.norm.num_batches_tracked) == 1


def test_voxelizer_half_precision_points_take_the_torch_form() -> None:
    pts = torch.from_numpy(_edge_cloud(np.random.default_rng(8), 300, 3).astype(np.float32)).half()
    got = voxelize([pts], **KW, max_points=3, max_pillars=8)
    assert got.pillars.dtype == torch.float16 and got.pillars.shape[0] == 8
    _assert_same_voxels(got, voxelize_torch([pts], **KW, max_points=3, max_pillars=8))


def test_bench_tool_compares_the_two_forms_on_a_model() -> None:
    """tools/bench_feature_extract.py's measurement: both forms on the same frames, their outputs compared (no timing
    is asserted)."""
    from helpers_tools import load_tool

    from detector.config import load_experiment
    from detector.models import build_model

    tool = load_tool("bench_feature_extract")
    model = build_model(load_experiment(ROOT / "detector" / "configs" / "mpchair_sparse_smoke.yaml").model).eval()
    rng = np.random.default_rng(2)
    frames = [rng.uniform([0, -4.8, -2], [6.4, 4.8, 2], size=(n, 3)).astype(np.float32) for n in (3000, 0, 800)]
    got = tool.run(model, frames, trials=2)
    assert got["voxels_bitwise_equal"] and got["features_max_abs_diff"] <= PFN_ATOL
    assert got["pillars_per_frame"] > 300 and set(got["ms_per_frame"]) == {"old", "new"}
    assert all(v > 0 for form in got["ms_per_frame"].values() for v in form.values())


# --- the real-points training path against the torch layers on the padded block -------------------------------------
def _training_batch(seed: int, p: int, t: int, c: int, dtype: torch.dtype = torch.float64):
    """Padded pillars (p, t, c) with 1..t real points each (some full), their counts and coords."""
    g = torch.Generator().manual_seed(seed)
    num = torch.randint(1, t + 1, (p,), generator=g)
    num[: max(1, p // 8)] = t  # full pillars: no padded slot takes part in their max
    pillars = (torch.rand(p, t, c, generator=g, dtype=dtype) - 0.3) * 3
    pillars[torch.arange(t)[None, :] >= num[:, None]] = 0
    coords = torch.stack([torch.zeros(p, dtype=torch.int64), torch.randint(0, 4, (p,), generator=g),
                          torch.randint(0, 4, (p,), generator=g)], dim=1)
    return pillars, num, coords


def test_compact_training_pillar_net_equals_torch_layers_in_float64() -> None:
    for seed, (p, t, c) in enumerate([(40, 8, 3), (60, 32, 4), (25, 1, 4), (30, 5, 3)]):
        torch.manual_seed(seed)
        net = PillarFeatureNet(in_channels=c, out_channels=16, voxel_size=VOXEL, point_cloud_range=RANGE)
        with torch.no_grad():  # channels with their ReLU mostly off and mostly on
            net.norm.weight.uniform_(0.5, 1.5)
            net.norm.bias.uniform_(-1.0, 0.5)
            net.norm.bias[:4] = -4.0  # ReLU off almost everywhere: the max is often 0 (a tie the gradient skips)
        net = net.double().train()
        ref = copy.deepcopy(net)
        pillars, num, coords = _training_batch(seed, p, t, c)
        grad = torch.randn(p, 16, dtype=torch.float64)
        assert net.compact_applies()
        out = net(pillars, num, coords)  # forward takes the compact path in training
        want = ref.forward_torch(pillars, num, coords)
        (out * grad).sum().backward()
        (want * grad).sum().backward()
        assert float((want[:, :4] == 0).double().mean()) > 0.3 and float((want[:, 4:] > 0).double().mean()) > 0.3
        np.testing.assert_allclose(out.detach().numpy(), want.detach().numpy(), atol=1e-11, rtol=1e-9)
        for (name, a), b in zip(net.named_parameters(), ref.parameters()):
            np.testing.assert_allclose(a.grad.numpy(), b.grad.numpy(), atol=1e-9, rtol=1e-9, err_msg=name)
        for name in ("running_mean", "running_var", "num_batches_tracked"):
            np.testing.assert_allclose(getattr(net.norm, name).numpy(), getattr(ref.norm, name).numpy(),
                                       atol=1e-12, rtol=1e-12, err_msg=name)


def test_compact_training_path_under_bf16_autocast_and_its_fallbacks() -> None:
    torch.manual_seed(3)
    net = PillarFeatureNet(in_channels=4, out_channels=16, voxel_size=VOXEL, point_cloud_range=RANGE).train()
    pillars, num, coords = _training_batch(5, 50, 16, 4, torch.float32)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = net.forward_compact(pillars, num, coords)
        want = copy.deepcopy(net).forward_torch(pillars, num, coords)
    assert got.dtype == want.dtype == torch.bfloat16  # the reference's output dtype under autocast
    np.testing.assert_allclose(got.float().detach().numpy(), want.float().detach().numpy(), atol=0.05, rtol=0.03)
    assert not net.eval().compact_applies()  # eval: running statistics, the fused or torch forms
    net.train()
    net.norm.momentum = None  # a cumulative-average BN: the torch layers
    assert not net.compact_applies()


def test_segment_max_gives_each_max_and_its_gradient_to_one_winner() -> None:
    """The training pillar net's max (``SegmentMax``): per pillar and channel the max of its rows and, for a pillar
    with padded slots, of the padding's value; the gradient goes to the winning row only: the first of tied rows, and
    a row rather than a tied padding (the slot order of the reference's ``max(dim=1)``)."""
    from detector.models.pillar_net import SegmentMax

    y = torch.tensor([[1.0, 0.0], [3.0, 0.0], [3.0, 2.0],  # pillar 0: rows 0-2, tied maxima in both channels
                      [0.5, 4.0],  # pillar 1: one row, padded
                      [float("nan"), 1.0], [7.0, 1.0]], dtype=torch.float64, requires_grad=True)  # pillar 2
    pad = torch.tensor([0.5, 0.25], dtype=torch.float64, requires_grad=True)
    offsets = torch.tensor([0, 3, 4, 6, 6])  # pillar 3: no rows (its padding, or 0 without)
    has_pad = torch.tensor([False, True, False, True])
    out = SegmentMax.apply(y, pad, offsets, has_pad)
    want = torch.tensor([[3.0, 2.0], [0.5, 4.0], [float("nan"), 1.0], [0.5, 0.25]], dtype=torch.float64)
    torch.testing.assert_close(out, want, equal_nan=True)
    grad = torch.tensor([[10.0, 20.0], [30.0, 40.0], [50.0, 60.0], [70.0, 80.0]], dtype=torch.float64)
    gy, gpad = torch.autograd.grad(out, (y, pad), grad)
    want_gy = torch.zeros(6, 2, dtype=torch.float64)
    want_gy[1, 0], want_gy[2, 1] = 10.0, 20.0  # the first of the tied 3.0s; channel 1's single max
    want_gy[3, 0], want_gy[3, 1] = 30.0, 40.0  # the row ties the padding in channel 0 and wins it
    want_gy[4, 0], want_gy[4, 1] = 50.0, 60.0  # NaN wins; the first of the tied 1.0s
    torch.testing.assert_close(gy, want_gy)
    torch.testing.assert_close(gpad, torch.tensor([70.0, 80.0], dtype=torch.float64))
