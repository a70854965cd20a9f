"""detector.models.voxelizer and pillar_net: caps and order against a slow reference, decorations by hand.

(Comparisons use numpy.testing: the first torch.testing.assert_close call imports ~10 s of CPU time.)"""

from __future__ import annotations

import copy
import math

import numpy as np
import torch

from detector.models.pillar_net import PillarFeatureNet
from detector.models.voxelizer import voxelize

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
