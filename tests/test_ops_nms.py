"""Greedy rotated NMS (detector.ops.nms) on numpy and torch, against a shapely brute force."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
import torch

from detector.ops import rotated_nms
from mpchair.geometry.boxes import bev_polygons


def brute_force_nms(boxes: np.ndarray, scores: np.ndarray, thr: float) -> list[int]:
    """Textbook greedy NMS with shapely IoU and a stable descending sort."""
    polys = shapely.polygons(bev_polygons(boxes))
    order = sorted(range(len(boxes)), key=lambda i: -scores[i])  # sorted() is stable: ties keep index order
    keep: list[int] = []
    for i in order:
        ok = True
        for k in keep:
            inter = polys[i].intersection(polys[k]).area
            if inter / (polys[i].area + polys[k].area - inter) > thr:
                ok = False
                break
        if ok:
            keep.append(i)
    return keep


def test_hand_made_case():
    boxes = np.array([
        [0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0],  # 0
        [0.5, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0],  # 1: IoU with 0 = 3.5*2 / (16 - 7) = 7/9
        [10.0, 0.0, 0.0, 4.0, 2.0, 1.5, 1.0],  # 2: alone
        [2.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0],  # 3: IoU with 0 = 1/3, with 1 = 5/11
    ])
    scores = np.array([0.5, 0.9, 0.1, 0.3])
    np.testing.assert_array_equal(rotated_nms(boxes, scores, 0.5), [1, 3, 2])  # 1 suppresses 0 (7/9 > 0.5)
    np.testing.assert_array_equal(rotated_nms(boxes, scores, 0.4), [1, 2])  # 3 too (5/11 > 0.4)
    np.testing.assert_array_equal(rotated_nms(boxes, scores, 0.8), [1, 0, 3, 2])
    assert rotated_nms(boxes, scores, 0.5).dtype == np.int64


def test_iou_equal_to_threshold_is_kept_and_ties_keep_index_order():
    a = np.array([[0.0, 0.0, 0.0, 2.0, 1.0, 1.0, 0.0], [1.0, 0.0, 0.0, 2.0, 1.0, 1.0, 0.0]])  # IoU exactly 1/3
    np.testing.assert_array_equal(rotated_nms(a, np.array([0.7, 0.7]), 1.0 / 3.0), [0, 1])
    np.testing.assert_array_equal(rotated_nms(a, np.array([0.7, 0.7]), 0.3), [0])
    np.testing.assert_array_equal(rotated_nms(a[::-1].copy(), np.array([0.7, 0.7]), 0.3), [0])
    same = np.repeat(np.array([[3.0, 1.0, 0.0, 1.0, 0.6, 0.9, 2.2]]), 5, axis=0)  # identical rotated boxes
    np.testing.assert_array_equal(rotated_nms(same, np.array([0.2, 0.9, 0.9, 0.1, 0.9]), 0.99), [1])


def test_matches_brute_force_on_random_scenes():
    rng = np.random.default_rng(11)
    for trial in range(10):
        n = int(rng.integers(1, 60))
        centres = rng.uniform(0, 8, (n, 2))
        boxes = np.c_[centres, rng.uniform(-1, 1, n), rng.uniform(0.4, 3, (n, 3)), rng.uniform(-math.pi, math.pi, n)]
        scores = np.round(rng.uniform(0, 1, n), 1)  # rounding makes ties common
        thr = [0.01, 0.1, 0.3, 0.5, 0.7][trial % 5]
        assert rotated_nms(boxes, scores, thr).tolist() == brute_force_nms(boxes, scores, thr)


def test_torch_tensors_in_and_out():
    rng = np.random.default_rng(5)
    boxes = np.c_[rng.uniform(0, 5, (40, 3)), rng.uniform(0.5, 2, (40, 3)), rng.uniform(-3, 3, 40)]
    scores = rng.uniform(0, 1, 40)
    expected = rotated_nms(boxes, scores, 0.2)
    kept = rotated_nms(torch.tensor(boxes, dtype=torch.float32), torch.tensor(scores, dtype=torch.float32), 0.2)
    assert kept.dtype == torch.int64 and kept.device.type == "cpu"
    # float32 inputs can only move IoUs by ~1e-7, far from any threshold crossing in this scene
    assert kept.tolist() == expected.tolist()
    assert 0 < len(expected) < 40
    empty = rotated_nms(torch.zeros((0, 7)), torch.zeros(0), 0.5)
    assert empty.shape == (0,) and empty.dtype == torch.int64


def test_bad_input():
    with pytest.raises(ValueError, match="scores"):
        rotated_nms(np.zeros((3, 7)), np.zeros(2), 0.5)
    with pytest.raises(ValueError, match="NaN"):
        rotated_nms(np.zeros((1, 7)), np.array([np.nan]), 0.5)
