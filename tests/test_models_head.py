"""Anchor head init, the exact sparse head, and post-processing (detector.models.{head,postprocess,backbone})."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from detector.models.anchors import generate_anchors
from detector.models.backbone import SecondBackbone
from detector.models.head import AnchorHead, SparseExactHead
from detector.models.postprocess import postprocess, select_candidates

CHAIR = (0.96, 0.667, 0.884)


@torch.no_grad()
def test_head_and_backbone_init_statistics() -> None:
    torch.manual_seed(0)
    head = AnchorHead(in_channels=384, num_anchors=2, num_classes=1)
    assert head.conv_cls.out_channels == 2 and head.conv_reg.out_channels == 14 and head.conv_dir.out_channels == 4
    assert torch.all(head.conv_cls.bias == torch.tensor(-math.log(99.0)))
    assert abs(float(head.conv_cls.bias[0]) + 4.59512) < 1e-4
    assert abs(float(head.conv_cls.weight.std()) - 0.01) < 0.0015
    assert abs(float(head.conv_reg.weight.std()) - 0.01) < 0.001
    assert float(head.conv_reg.bias.abs().max()) == 0.0
    bb = SecondBackbone(in_channels=64, layer_channels=(64, 128, 256), layer_nums=(3, 5, 5), layer_strides=(2, 2, 2))
    convs = [m for m in bb.modules() if isinstance(m, torch.nn.Conv2d)]
    assert len(convs) == 4 + 6 + 6 and all(c.bias is None for c in convs)
    w = convs[-1].weight  # 256 → 256, 3x3: Kaiming fan_out std sqrt(2 / (256 * 9))
    assert abs(float(w.std()) / math.sqrt(2 / (256 * 9)) - 1) < 0.02
    bns = [m for m in bb.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    assert all(b.eps == 1e-3 and b.momentum == 0.01 for b in bns)


def test_sparse_exact_head_equals_dense_head_and_detections() -> None:
    torch.manual_seed(1)
    dense = AnchorHead(in_channels=16, num_anchors=2, num_classes=1)
    sparse = SparseExactHead(in_channels=16, num_anchors=2, num_classes=1)
    with torch.no_grad():
        dense.conv_cls.bias.zero_()  # every inactive anchor scores exactly 0.5: a top-k full of ties
        dense.conv_dir.weight.mul_(10)
    sparse.load_state_dict(dense.state_dict())
    h, w = 16, 16
    active = torch.rand(2, h, w) < 0.1
    x = torch.randn(2, 16, h, w) * active[:, None].float()  # zero off the active set, like todense output
    with torch.no_grad():
        a, b = dense(x), sparse(x, active)
        assert torch.equal(sparse(x, None).cls, a.cls)  # no mask → the dense path
    for da, sa in zip(a, b):
        assert da.shape == sa.shape
        assert torch.equal(da[~active], sa[~active])  # inactive sites: exactly the bias
        assert float((da - sa).abs().max()) < 1e-6
    anchors = generate_anchors(
        feature_size=(h, w), anchor_range=(0, -4, 0, 8, 4, 0), sizes=[CHAIR], rotations=(0.0, 1.57)
    )
    kw = dict(num_classes=1, nms_pre=100, score_thr=0.1, nms_iou=0.01)
    da, sa = postprocess(*a, anchors, **kw), postprocess(*b, anchors, **kw)
    assert len(da) == 2 and len(da[0].boxes) > 5
    for d, s in zip(da, sa):
        assert d.boxes.shape == s.boxes.shape and torch.equal(d.labels, s.labels)
        np.testing.assert_allclose(d.boxes.numpy(), s.boxes.numpy(), atol=1e-6)
        np.testing.assert_allclose(d.scores.numpy(), s.scores.numpy(), atol=1e-6)


def test_postprocess_constructed_predictions() -> None:
    anchors = generate_anchors(
        feature_size=(2, 2), anchor_range=(0, 0, 0, 10, 10, 0), sizes=[CHAIR], rotations=(0.0, 1.57)
    )  # cells (iy, ix) at x = 10 ix, y = 10 iy
    cls = torch.full((2, 2, 2, 2), -10.0)  # (B, H, W, A*K), channel = rotation
    reg = torch.zeros(2, 2, 2, 14)
    dirs = torch.zeros(2, 2, 2, 4)
    cls[0, 0, 0, 0], cls[0, 0, 0, 1] = 3.0, 2.0  # same cell, both rotations: the second is suppressed by NMS
    cls[0, 0, 1, 0] = 1.0
    cls[0, 1, 0, 1] = -1.0  # score 0.269 > 0.1
    cls[0, 1, 1, 0] = -3.0  # score 0.047 < 0.1 and outside the top-k (nms_pre = 4)
    dirs[0, 0, 0, 1] = 1.0  # anchor (0, 0, rot 0): direction bin 1 → yaw 0 + pi
    reg[0, 0, 1, 0] = 0.1  # dx of anchor (0, 1, rot 0)
    reg[0, 1, 0, 7 + 6] = 0.2  # dr of anchor (1, 0, rot 1)
    dets = postprocess(cls, reg, dirs, anchors, num_classes=1, nms_pre=4, score_thr=0.1, nms_iou=0.01)
    d = math.hypot(CHAIR[0], CHAIR[1])
    zc = CHAIR[2] / 2
    expected = np.array(
        [
            [0.0, 0.0, zc, *CHAIR, math.pi],
            [10.0 + 0.1 * d, 0.0, zc, *CHAIR, 0.0],
            [0.0, 10.0, zc, *CHAIR, 1.77],
        ]
    )
    np.testing.assert_allclose(dets[0].boxes.numpy(), expected, atol=1e-5)
    sig = [1 / (1 + math.exp(-v)) for v in (3.0, 1.0, -1.0)]
    np.testing.assert_allclose(dets[0].scores.numpy(), sig, rtol=1e-6)
    assert dets[0].labels.tolist() == [0, 0, 0]
    assert dets[1].boxes.shape == (0, 7) and dets[1].scores.shape == (0,)


@pytest.mark.parametrize("num_classes", [1, 3])
def test_candidates_are_the_top_k_anchors_that_can_pass_the_score_threshold(num_classes: int) -> None:
    """select_candidates scans only anchors above the score cut, yet keeps exactly what "top nms_pre by max class score,
    then score > score_thr" keeps, on channel-planar and interleaved maps alike, highest score first."""
    g = torch.Generator().manual_seed(0)
    h, w, a = 12, 10, 2
    planar = torch.randn(a * num_classes, h, w, generator=g) * 2 - 2  # (C, H, W) memory, like the head's output
    for cls in (planar.permute(1, 2, 0), planar.permute(1, 2, 0).contiguous()):  # (H, W, A*K) views
        scores = torch.sigmoid(cls.reshape(-1, num_classes))  # rows in anchor order (iy * W + ix) * A + a
        best = scores.max(dim=1).values
        for nms_pre, thr in ((5, 0.1), (40, 0.1), (1000, 0.1), (50, 0.3), (50, 0.0), (50, 1.0)):
            idx, sc = select_candidates(cls, num_classes=num_classes, nms_pre=nms_pre, score_thr=thr)
            top = torch.topk(best, min(nms_pre, len(best))).indices
            expected = set(top[best[top] > thr].tolist())
            assert set(idx[best[idx] > thr].tolist()) == expected, (nms_pre, thr)
            assert len(idx) <= nms_pre and len(set(idx.tolist())) == len(idx)
            torch.testing.assert_close(sc, scores[idx], atol=1e-7, rtol=0)
            assert torch.all(best[idx][:-1] >= best[idx][1:])  # highest first
        assert len(select_candidates(cls, num_classes=num_classes, nms_pre=1000, score_thr=0.1)[0]) > 40  # cut bites
