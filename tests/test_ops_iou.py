"""Exact rotated IoU (detector.ops.iou) against shapely, plus the degenerate cases the reference kernel gets wrong."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st

from detector.ops import (
    bev_intersection_area,
    camera_boxes,
    camera_to_sensor_style,
    iou_3d,
    iou_3d_camera,
    rotated_iou_bev,
    rotated_iou_bev_camera,
)
from mpchair.geometry.boxes import bev_polygons


def shapely_iou(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, M) BEV intersection and IoU by shapely for sensor boxes."""
    pa = shapely.polygons(bev_polygons(a))[:, None]
    pb = shapely.polygons(bev_polygons(b))[None, :]
    inter = shapely.area(shapely.intersection(pa, pb))
    union = shapely.area(pa) + shapely.area(pb) - inter
    return inter, np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)


def camera_polygon(box: np.ndarray) -> shapely.Polygon:
    """KITTI BEV rectangle straight from the reference's corner formula in the camera x-z plane."""
    x, _, z, l, _, w, ry = box
    pts = []
    for sl, sw in ((1, -1), (1, 1), (-1, 1), (-1, -1)):
        ox, oz = sl * l / 2, sw * w / 2
        pts.append((x + math.cos(ry) * ox + math.sin(ry) * oz, z - math.sin(ry) * ox + math.cos(ry) * oz))
    return shapely.Polygon(pts)


coord = st.floats(-4, 4, allow_nan=False)
size = st.floats(0.05, 5, allow_nan=False)
angle = st.floats(-7, 7, allow_nan=False)
box_st = st.tuples(coord, coord, coord, size, size, size, angle)


@settings(max_examples=50, deadline=None)
@given(st.lists(box_st, min_size=1, max_size=4), st.lists(box_st, min_size=1, max_size=4))
def test_bev_iou_matches_shapely(a, b):
    a, b = np.array(a), np.array(b)
    inter_ref, iou_ref = shapely_iou(a, b)
    np.testing.assert_allclose(bev_intersection_area(a, b), inter_ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(rotated_iou_bev(a, b), iou_ref, rtol=0, atol=1e-9)


@settings(max_examples=25, deadline=None)
@given(st.lists(box_st, min_size=1, max_size=3), st.lists(box_st, min_size=1, max_size=3))
def test_iou_3d_matches_shapely_times_height(a, b):
    a, b = np.array(a), np.array(b)
    inter_bev, _ = shapely_iou(a, b)
    top = np.minimum(a[:, None, 2] + a[:, None, 5] / 2, b[None, :, 2] + b[None, :, 5] / 2)
    bottom = np.maximum(a[:, None, 2] - a[:, None, 5] / 2, b[None, :, 2] - b[None, :, 5] / 2)
    inter = inter_bev * np.clip(top - bottom, 0, None)
    vol = a[:, None, 3] * a[:, None, 4] * a[:, None, 5] + b[None, :, 3] * b[None, :, 4] * b[None, :, 5]
    np.testing.assert_allclose(iou_3d(a, b), inter / (vol - inter), rtol=0, atol=1e-9)


def test_random_far_boxes_match_shapely():
    # 60 m from the origin (KITTI range): the kernel works relative to a's centre, so no digits are lost.
    rng = np.random.default_rng(3)
    n = 40
    a = np.c_[rng.uniform(55, 60, (n, 2)), rng.uniform(-1, 1, n), rng.uniform(0.3, 4, (n, 3)), rng.uniform(-4, 4, n)]
    b = a + np.c_[rng.normal(0, 0.5, (n, 2)), np.zeros(n), rng.normal(0, 0.2, (n, 3)), rng.normal(0, 0.3, n)]
    b[:, 3:6] = np.abs(b[:, 3:6])
    _, ref = shapely_iou(a, b)
    got = rotated_iou_bev(a, b)
    assert (np.diag(got) > 0.05).sum() > 30  # most pairs overlap substantially
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-10)


@pytest.mark.parametrize("yaw", [0.0, 0.3, math.pi / 4, 1.0, math.pi / 2, 2.5, -math.pi, -0.7])
def test_identical_rotated_boxes_score_exactly_one(yaw):
    boxes = np.array([[12.34, -5.67, 0.4, 3.9, 1.6, 1.5, yaw], [0.1, 0.2, 0.3, 0.41, 0.37, 0.9, yaw]])
    assert np.all(np.diag(rotated_iou_bev(boxes, boxes)) == 1.0)
    assert np.all(np.diag(iou_3d(boxes, boxes)) == 1.0)
    assert np.all(np.diag(bev_intersection_area(boxes, boxes)) == boxes[:, 3] * boxes[:, 4])
    cam = camera_boxes(boxes[:, :3], boxes[:, [5, 4, 3]], boxes[:, 6])  # any valid camera boxes
    assert np.all(np.diag(rotated_iou_bev_camera(cam, cam)) == 1.0)
    assert np.all(np.diag(iou_3d_camera(cam, cam)) == 1.0)


def test_same_rectangle_other_yaw_is_one_to_rounding():
    a = np.array([[1.0, 2.0, 0.0, 4.0, 2.0, 1.0, 0.7]])
    for shift in (math.pi, 2 * math.pi, -math.pi):
        b = a.copy()
        b[0, 6] += shift
        assert rotated_iou_bev(a, b)[0, 0] == pytest.approx(1.0, abs=1e-12)
    square = np.array([[0.0, 0.0, 0.0, 2.0, 2.0, 1.0, 0.2]])
    turned = square.copy()
    turned[0, 6] += math.pi / 2  # a square turned by 90 degrees is the same square
    assert rotated_iou_bev(square, turned)[0, 0] == pytest.approx(1.0, abs=1e-12)


def test_contained_box_gives_its_area_exactly():
    big = np.array([[0.0, 0.0, 0.0, 6.0, 4.0, 2.0, 0.4]])
    small = np.array([[0.3, -0.2, 0.0, 2.0, 1.0, 2.0, 1.3]])
    assert bev_intersection_area(big, small)[0, 0] == 2.0
    assert bev_intersection_area(small, big)[0, 0] == 2.0
    assert rotated_iou_bev(big, small)[0, 0] == 2.0 / 24.0
    # Touching the inside of an edge: still its own area (up to one rounding of the rotation).
    inner = np.array([[1.0, 0.0, 0.0, 4.0, 4.0, 2.0, 0.0]])
    outer = np.array([[0.0, 0.0, 0.0, 6.0, 4.0, 2.0, 0.0]])
    assert bev_intersection_area(inner, outer)[0, 0] == 16.0
    assert iou_3d(inner, outer)[0, 0] == 16.0 / 24.0


def test_touching_and_disjoint_boxes_give_zero():
    a = np.array([[0.0, 0.0, 0.0, 2.0, 2.0, 1.0, 0.0]])
    edge = np.array([[2.0, 0.0, 0.0, 2.0, 2.0, 1.0, 0.0]])  # shares the x = 1 edge
    corner = np.array([[2.0, 2.0, 0.0, 2.0, 2.0, 1.0, 0.0]])  # shares one corner
    rotated = np.array([[1.0 + math.sqrt(2), 0.0, 0.0, 2.0, 2.0, 1.0, math.pi / 4]])  # diamond touching the edge
    far = np.array([[50.0, 0.0, 0.0, 2.0, 2.0, 1.0, 0.3]])
    for b in (edge, corner, rotated, far):
        assert abs(rotated_iou_bev(a, b)[0, 0]) < 1e-12
    stacked = np.array([[0.0, 0.0, 1.0, 2.0, 2.0, 1.0, 0.0]])  # on top of a: BEV overlap 1, no volume overlap
    assert rotated_iou_bev(a, stacked)[0, 0] == 1.0
    assert iou_3d(a, stacked)[0, 0] == 0.0


def test_half_overlap_hand_computed():
    a = np.array([[0.0, 0.0, 0.0, 2.0, 1.0, 2.0, 0.0]])
    b = np.array([[1.0, 0.0, 0.5, 2.0, 1.0, 1.0, 0.0]])
    assert rotated_iou_bev(a, b)[0, 0] == pytest.approx(1.0 / 3.0, abs=1e-15)
    # 3D: BEV 1 m^2 x height overlap 1 (a spans z -1..1, b 0..1); volumes 4 and 2 -> 1 / (6 - 1).
    assert iou_3d(a, b)[0, 0] == pytest.approx(1.0 / 5.0, abs=1e-15)
    # 45-degree square over an axis-aligned one of the same centre: octagon area 8 (sqrt 2 - 1) for side 2.
    sq = np.array([[0.0, 0.0, 0.0, 2.0, 2.0, 1.0, 0.0]])
    diamond = np.array([[0.0, 0.0, 0.0, 2.0, 2.0, 1.0, math.pi / 4]])
    octagon = 8 * (math.sqrt(2) - 1)
    assert bev_intersection_area(sq, diamond)[0, 0] == pytest.approx(octagon, abs=1e-14)


def test_zero_and_negative_sizes_overlap_nothing():
    a = np.array([[0.0, 0.0, 0.0, 2.0, 2.0, 1.0, 0.0]])
    flat = np.array([[0.0, 0.0, 0.0, 2.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
                     [0.0, 0.0, 0.0, -1.0, -1.0, -1.0, -10.0], [0.0, 0.0, 0.0, 2.0, 2.0, 0.0, 0.0]])
    assert np.all(bev_intersection_area(a, flat)[0, :3] == 0.0)
    assert np.all(rotated_iou_bev(a, flat)[0, :3] == 0.0)
    assert np.all(rotated_iou_bev(flat, flat)[:3, :3] == 0.0)  # even "identical" zero-area boxes
    assert np.all(iou_3d(a, flat)[0] == 0.0)  # the last one has no height
    assert np.all(iou_3d(flat, flat) == 0.0)
    assert rotated_iou_bev(np.zeros((0, 7)), a).shape == (0, 1)
    with pytest.raises(ValueError, match=r"\(N, 7\)"):
        rotated_iou_bev(np.zeros((3, 5)), a)


def test_camera_bev_matches_reference_corner_formula():
    rng = np.random.default_rng(7)
    n = 30
    loc = np.c_[rng.uniform(-3, 3, n), rng.uniform(1, 2, n), rng.uniform(8, 14, n)]
    hwl = rng.uniform(0.5, 4, (n, 3))
    ry = rng.uniform(-math.pi, math.pi, n)
    cam = camera_boxes(loc, hwl, ry)
    np.testing.assert_array_equal(cam[:, 3:6], hwl[:, [2, 0, 1]])  # [l, h, w]
    polys = [camera_polygon(c) for c in cam]
    ref = np.array([[p.intersection(q).area / p.union(q).area for q in polys] for p in polys])
    got = rotated_iou_bev_camera(cam, cam)
    assert (got > 0.01).sum() > n  # off-diagonal overlaps exist
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-10)
    # 3D: y is the bottom, the box spans y - h .. y (y down).
    inter_bev = np.array([[p.intersection(q).area for q in polys] for p in polys])
    y, h = cam[:, 1], cam[:, 4]
    iw = np.clip(np.minimum(y[:, None], y[None]) - np.maximum((y - h)[:, None], (y - h)[None]), 0, None)
    vol = cam[:, 3] * cam[:, 4] * cam[:, 5]
    inter = inter_bev * iw
    np.testing.assert_allclose(iou_3d_camera(cam, cam), inter / (vol[:, None] + vol[None] - inter), atol=1e-10)


def test_camera_to_sensor_style_axes():
    # ry = 0: l along camera +x, which is sensor -y; the box faces camera +x, i.e. heading -pi/2.
    cam = np.array([[1.0, 1.5, 10.0, 4.0, 1.5, 2.0, 0.0]])
    s = camera_to_sensor_style(cam)
    np.testing.assert_allclose(s, [[10.0, -1.0, -0.75, 4.0, 2.0, 1.5, -math.pi / 2]])
    poly = bev_polygons(s)[0]
    assert np.ptp(poly[:, 1]) == pytest.approx(4.0) and np.ptp(poly[:, 0]) == pytest.approx(2.0)


def test_3d_iou_never_exceeds_bev_iou():
    """The fact docs/evaluation.md and the report's recall-blind note rest on: for upright boxes, IoU_3D =
    I*h_i / (A*h_a + B*h_b - I*h_i) <= I / (A + B - I) = IoU_BEV, since h_i <= min(h_a, h_b)."""
    from detector.ops import iou_3d, rotated_iou_bev

    rng = np.random.default_rng(41)
    a = np.column_stack([rng.uniform(-2, 2, (200, 3)), rng.uniform(0.2, 3, (200, 3)), rng.uniform(-np.pi, np.pi, 200)])
    shift = np.column_stack([rng.normal(0, 0.4, (200, 3)), rng.normal(0, 0.3, (200, 3)).clip(-0.15),
                             rng.normal(0, 0.5, 200)])
    b = a + shift
    bev, d3 = rotated_iou_bev(a, b), iou_3d(a, b)
    assert (d3 > 0.2).sum() > 50  # many overlapping pairs, not a vacuous check
    assert np.all(d3 <= bev + 1e-12)
