"""Anchors, box coder, nearest-BEV assignment and losses (detector.models.{anchors,box_coder,assign,losses})."""

from __future__ import annotations

import math

import numpy as np
import torch

from detector.models.anchors import generate_anchors
from detector.models.assign import assign_targets, axis_aligned_iou, direction_bin, nearest_bev
from detector.models.box_coder import decode_boxes, encode_boxes, limit_period
from detector.models.head import HeadOutput
from detector.models.losses import Losses, compute_loss, sigmoid_focal_loss, smooth_l1
from mpchair.geometry import wrap_angle

CHAIR = (0.960005934232471, 0.6668719666706728, 0.8838318530669755)


def test_matterport_anchor_count_order_and_positions() -> None:
    a = generate_anchors(
        feature_size=(384, 256), anchor_range=(0, -19, 0, 25, 19, 0), sizes=[CHAIR], rotations=(0.0, 1.57)
    )
    assert a.shape == (196_608, 7)
    xs, ys = np.linspace(0, 25, 256), np.linspace(-19, 19, 384)
    for iy, ix, r in [(0, 0, 0), (0, 0, 1), (0, 1, 0), (1, 0, 1), (383, 255, 1), (200, 17, 0)]:
        row = a[(iy * 256 + ix) * 2 + r].double().numpy()
        expected = [xs[ix], ys[iy], CHAIR[2] / 2, *CHAIR, (0.0, 1.57)[r]]  # z: bottom 0 → centre h/2
        np.testing.assert_allclose(row, expected, atol=1e-5)


def test_anchor_memory_order_sizes_then_rotations() -> None:
    a = generate_anchors(
        feature_size=(2, 3), anchor_range=(0, 0, -1, 2, 1, -1), sizes=[(4, 2, 1), (1, 1, 2)], rotations=(0.0, 1.0, 2.0)
    )
    assert a.shape == (2 * 3 * 2 * 3, 7)
    a = a.view(2, 3, 2, 3, 7)  # (y, x, size, rot)
    assert a[1, 2, 1, 2].tolist() == [2.0, 1.0, 0.0, 1.0, 1.0, 2.0, 2.0]
    assert a[0, 1, 0, 1].tolist() == [1.0, 0.0, -0.5, 4.0, 2.0, 1.0, 1.0]


def test_cell_anchors_sit_at_the_head_map_cell_centres() -> None:
    """``cells`` placement: origin + (i + 1/2) * cell on each axis, z from the anchor range, same memory order."""
    a = generate_anchors(feature_size=(4, 3), anchor_range=(9, 9, -1, 99, 99, -1), sizes=[(4, 2, 1)],
                         rotations=(0.0, 1.0), cells=(0.0, -0.4, 0.1, 0.2)).view(4, 3, 1, 2, 7)
    np.testing.assert_allclose(a[:, 0, 0, 0, 1].double().numpy(), [-0.3, -0.1, 0.1, 0.3], atol=1e-6)
    np.testing.assert_allclose(a[0, :, 0, 1, 0].double().numpy(), [0.05, 0.15, 0.25], atol=1e-6)
    assert a[2, 1, 0, 1, 2:].tolist() == [-0.5, 4.0, 2.0, 1.0, 1.0]


def test_weights_moved_to_another_grid_keep_their_anchors(tmp_path) -> None:
    """The CPU configs' weights loaded into the 768 x 512 model: every head cell over the 288 x 144 area gets an
    anchor within 1 mm of the trained one (both grids cell-centred), and a checkpoint trained with the reference's
    linspace anchors moves within its own drift (±5 cm), not the 9-39 cm by which the 768 x 512 linspace anchors sit
    from the 288 x 144 ones at the same place (every box would be off by that)."""
    import dataclasses
    import warnings

    from detector.checkpoint import Checkpoint, load_model, save_checkpoint
    from detector.config import load_experiment
    from detector.models import build_model

    big = load_experiment("detector/configs/mpchair_dense.yaml")
    for centres, tol in (("cells", 1e-3), ("range", 0.051)):
        small = load_experiment("detector/configs/mpchair_dense_cpu.yaml")
        small = dataclasses.replace(small, model=dataclasses.replace(small.model, anchor_centres=centres))
        model = build_model(small.model)
        ckpt = tmp_path / f"{centres}.pt"
        save_checkpoint(ckpt, Checkpoint.capture(model=model, optimizer=torch.optim.AdamW(model.parameters()),
                                                 cfg=small, epoch=0, step_in_epoch=0, step=0, global_batch=1))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            moved = load_model(big, ckpt)
        assert any("anchors at the head map's cell centres" in str(w.message) for w in caught)
        # head cells are 0.1 m; the small grid's cell (iy, ix) is the big one's (iy + 118, ix): y -7.2 vs -19.0
        a_small = model.anchors.view(144, 72, 2, 7)[..., :2].double()
        a_big = moved.anchors.view(384, 256, 2, 7)[118:118 + 144, :72, :, :2].double()
        assert (a_big - a_small).abs().max().item() < tol
        reference = build_model(big.model).anchors.view(384, 256, 2, 7)[118:118 + 144, :72, :, :2].double()
        assert (reference - a_small).abs().max().item() > 0.15  # what the grid move gave before


def test_box_coder_known_values_and_round_trip() -> None:
    anchor = torch.tensor([[1.0, 2.0, 0.5, 3.0, 4.0, 1.0, 0.25]], dtype=torch.float64)  # diagonal d = 5
    box = torch.tensor([[6.0, -3.0, 1.5, 6.0, 2.0, math.e, -0.75]], dtype=torch.float64)
    d = encode_boxes(box, anchor)
    np.testing.assert_allclose(d.numpy(), [[1.0, -1.0, 1.0, math.log(2), math.log(0.5), 1.0, -1.0]], atol=1e-12)
    g = torch.Generator().manual_seed(1)
    anchors = torch.rand(50, 7, generator=g, dtype=torch.float64) + 0.2
    boxes = torch.rand(50, 7, generator=g, dtype=torch.float64) * 3 + 0.1
    np.testing.assert_allclose(decode_boxes(encode_boxes(boxes, anchors), anchors).numpy(), boxes.numpy(), atol=1e-12)


def test_limit_period_matches_geometry_wrap_angle() -> None:
    a = np.random.default_rng(0).uniform(-20, 20, 200)
    for offset, period in [(0.5, 2 * math.pi), (0.0, math.pi), (0.0, 2 * math.pi), (1.0, math.pi)]:
        ours = limit_period(torch.from_numpy(a), offset, period).numpy()
        np.testing.assert_allclose(ours, wrap_angle(a, offset, period), atol=1e-12)


def test_nearest_bev_swap_and_iou() -> None:
    b = torch.tensor(
        [
            [0.0, 0.0, 0.0, 4.0, 2.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 4.0, 2.0, 1.0, 0.7],  # |yaw| < pi/4: no swap
            [0.0, 0.0, 0.0, 4.0, 2.0, 1.0, 0.8],  # > pi/4: swap
            [0.0, 0.0, 0.0, 4.0, 2.0, 1.0, -math.pi / 2],  # swap
            [0.0, 0.0, 0.0, 4.0, 2.0, 1.0, 3.0],  # wraps to -0.14: no swap
        ],
        dtype=torch.float64,
    )
    r = nearest_bev(b)
    assert r.tolist() == [[-2, -1, 2, 1], [-2, -1, 2, 1], [-1, -2, 1, 2], [-1, -2, 1, 2], [-2, -1, 2, 1]]
    iou = axis_aligned_iou(torch.tensor([[0.0, 0, 2, 2]]), torch.tensor([[1.0, 1, 3, 3], [5.0, 5, 6, 6]]))
    np.testing.assert_allclose(iou.numpy(), [[1 / 7, 0.0]], atol=1e-7)
    assert direction_bin(torch.tensor([0.1, 3.2, -0.1, math.pi / 2, -3.0])).tolist() == [0, 1, 1, 0, 1]


def _box(x, y, l, w, yaw=0.0):
    return [x, y, 0.0, l, w, 1.0, yaw]


def test_assignment_hand_cases() -> None:
    gts = torch.tensor(
        [
            _box(0, 1, 2, 2, -0.1),  # gt0: [-1, 1] x [0, 2]
            _box(0, 0, 4, 1),  # gt1: [-2, 2] x [-0.5, 0.5], no good anchor
            _box(10, 0, 2, 2),  # gt2: two anchors tie for its best
            _box(30, 0, 2, 1, math.pi / 2),  # gt3: x extent 1, y extent 2 after the swap
        ],
        dtype=torch.float64,
    )
    anchors = torch.tensor(
        [
            _box(0, 1, 2, 2),  # a0: IoU 1 with gt0 → positive (gt0)
            _box(0, 0.5, 2, 2),  # a1: IoU 0.6 gt0 (ignore zone) but gt1's best (1/3 >= 0.3) → positive toward gt1
            _box(20, 20, 2, 2),  # a2: far → negative
            _box(0.6, 1, 2, 2),  # a3: IoU 0.538 gt0, 1/7 gt1, nobody's best → ignored
            _box(10.75, 0, 2, 2),  # a4, a5: IoU 2.5/5.5 with gt2 each, tied best → both positive
            _box(9.25, 0, 2, 2),
            _box(30, 0, 1, 2),  # a6: same rectangle as gt3 → IoU 1
            _box(30, 0, 2, 1),  # a7: crossed rectangle, IoU 1/3 → ignored
        ],
        dtype=torch.float64,
    )
    labels = torch.tensor([0, 1, 0, 1])
    t = assign_targets(anchors, [gts], [labels], pos_iou_thr=0.7, neg_iou_thr=0.3)
    assert t.pos[0].tolist() == [True, True, False, False, True, True, True, False]
    assert t.neg[0].tolist() == [False, False, True, False, False, False, False, False]
    assert t.labels[0][t.pos[0]].tolist() == [0, 1, 0, 0, 1]
    assigned = [0, 1, 2, 2, 3]
    pos_idx = torch.nonzero(t.pos[0]).squeeze(1)
    np.testing.assert_allclose(t.reg[0, pos_idx].numpy(), encode_boxes(gts[assigned], anchors[pos_idx]).numpy())
    assert t.dir[0, pos_idx].tolist() == [1, 0, 0, 0, 0]  # gt0 yaw -0.1 wraps to 2pi - 0.1 → bin 1
    # a1 regresses toward gt1 (dy = -0.5 / d), not toward its argmax gt0 (dy = +0.5 / d).
    assert math.isclose(float(t.reg[0, 1, 1]), -0.5 / math.sqrt(8), abs_tol=1e-12)
    # No GT: every anchor negative. Batch of two stacks per sample.
    t = assign_targets(anchors, [gts, gts[:0]], [labels, labels[:0]], pos_iou_thr=0.7, neg_iou_thr=0.3)
    assert t.pos.shape == (2, 8) and not bool(t.pos[1].any()) and bool(t.neg[1].all())


def test_focal_and_smooth_l1_known_values() -> None:
    ln2 = math.log(2)
    fl = sigmoid_focal_loss(torch.zeros(2), torch.tensor([1.0, 0.0]), 0.25, 2.0)
    np.testing.assert_allclose(fl.numpy(), [0.25 * 0.25 * ln2, 0.75 * 0.25 * ln2], rtol=1e-6)
    fl = sigmoid_focal_loss(torch.tensor([2.0]), torch.tensor([1.0]), 0.25, 2.0)
    p = 1 / (1 + math.exp(-2))
    np.testing.assert_allclose(fl.numpy(), [0.25 * (1 - p) ** 2 * -math.log(p)], rtol=1e-6)
    np.testing.assert_allclose(
        smooth_l1(torch.tensor([0.05, -1.0]), 0.11).numpy(), [0.5 * 0.0025 / 0.11, 0.945], rtol=1e-6
    )


def test_compute_loss_known_values() -> None:
    # One cell with A = 3 anchors, K = 1: anchor 0 positive, 1 negative, 2 ignored (its huge logit must not count).
    cls = torch.tensor([0.0, 0.0, 50.0]).view(1, 1, 1, 3)
    reg = torch.zeros(1, 1, 1, 21)
    dirs = torch.zeros(1, 1, 1, 6)
    reg_t = torch.zeros(1, 3, 7)
    reg_t[0, 0, 0], reg_t[0, 0, 6] = 0.05, 0.5
    from detector.models.assign import Targets

    t = Targets(
        torch.zeros(1, 3, dtype=torch.int64),
        torch.tensor([[True, False, False]]),
        torch.tensor([[False, True, False]]),
        reg_t,
        torch.tensor([[1, 0, 0]]),
    )
    out = compute_loss(HeadOutput(cls, reg, dirs), t, num_classes=1)
    ln2 = math.log(2)
    cls_exp = 0.25 * 0.25 * ln2 + 0.75 * 0.25 * ln2
    reg_exp = 2.0 * (0.5 * 0.05**2 / 0.11 + (math.sin(0.5) - 0.055))  # yaw: sin(0)cos(.5) vs cos(0)sin(.5)
    dir_exp = 0.2 * ln2
    assert isinstance(out, Losses) and all(v.dim() == 0 for v in out)
    got = {k: float(v) for k, v in out._asdict().items()}
    np.testing.assert_allclose(
        [got["cls"], got["reg"], got["dir"], got["total"]],
        [cls_exp, reg_exp, dir_exp, cls_exp + reg_exp + dir_exp],
        rtol=1e-5,
    )
    # No positives: normalised by max(1, 0) = 1, reg and dir are 0.
    t0 = Targets(t.labels, torch.zeros(1, 3, dtype=torch.bool), torch.tensor([[True, True, False]]), reg_t, t.dir)
    out = compute_loss(HeadOutput(cls, reg, dirs), t0, num_classes=1)
    np.testing.assert_allclose(
        [float(out.cls), float(out.reg), float(out.dir)], [2 * 0.75 * 0.25 * ln2, 0.0, 0.0], rtol=1e-5
    )
