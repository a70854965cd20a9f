"""Frames, boxes, camera conversions, projection and the pillar rule, against hand values and slow references."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mpchair.geometry import (
    SENSOR_TO_CAMERA,
    bev_polygons,
    box_corners,
    boxes_to_kitti_camera,
    fov_mask,
    grid_size,
    invert_rigid,
    kitti_camera_to_boxes,
    make_tr_velo_to_cam,
    pillar_coords,
    points_in_boxes,
    project_boxes_to_image,
    rigid_from,
    transform_boxes,
    transform_points,
    wrap_angle,
    yaw_matrix,
    yaw_of,
)
from mpchair.kitti import Calib

PI = math.pi


def random_boxes(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.c_[rng.uniform(-10, 10, (n, 3)), rng.uniform(0.2, 4, (n, 3)), rng.uniform(-PI, PI, n)]


def random_rigid(rng: np.random.Generator, yaw_only: bool) -> np.ndarray:
    if yaw_only:
        R = yaw_matrix(rng.uniform(-PI, PI))[:3, :3]
    else:
        q, r = np.linalg.qr(rng.normal(size=(3, 3)))
        R = q * np.sign(np.diag(r))
        R = R * np.linalg.det(R)  # proper rotation
    return rigid_from(R, rng.uniform(-5, 5, 3))


def simple_calib(f: float = 100.0, cx: float = 100.0, cy: float = 50.0, t=(0.0, 0.0, 0.0)) -> Calib:
    """A pinhole P2 (no baseline), R0_rect = I and the pure sensor → camera axis swap."""
    P = np.array([[f, 0, cx, 0], [0, f, cy, 0], [0, 0, 1, 0]], dtype=float)
    return Calib(P0=P, P1=P, P2=P, P3=P, R0_rect=np.eye(3), Tr_velo_to_cam=make_tr_velo_to_cam(t),
                 Tr_imu_to_velo=np.eye(3, 4))  # fmt: skip


# ---------------------------------------------------------------------------------------------------------- angles
@given(st.floats(-1e6, 1e6, allow_nan=False))
@settings(max_examples=100, deadline=None)
def test_wrap_angle_range_and_equivalence(a):
    w = float(wrap_angle(a))
    assert -PI <= w < PI
    assert math.isclose(math.cos(w), math.cos(a), abs_tol=1e-9 * max(1.0, abs(a)))
    assert math.isclose(math.sin(w), math.sin(a), abs_tol=1e-9 * max(1.0, abs(a)))
    w0 = float(wrap_angle(a, offset=0.0))
    assert 0 <= w0 < 2 * PI


def test_wrap_angle_hand_values():
    np.testing.assert_allclose(wrap_angle([PI, -PI, 3 * PI / 2, -3 * PI / 2, 0.0, 7.0]),
                               [-PI, -PI, -PI / 2, PI / 2, 0.0, 7.0 - 2 * PI])  # fmt: skip
    assert float(wrap_angle(-1e-17)) == -1e-17  # rounding never lands on +pi
    assert float(wrap_angle(1.0, period=1.0, offset=0.0)) == 0.0
    assert wrap_angle(np.float32(1.0)).dtype == np.float64


# ------------------------------------------------------------------------------------------------------- transforms
def test_rigid_helpers_hand_values():
    T = yaw_matrix(PI / 2)
    np.testing.assert_allclose(T, [[0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], atol=1e-15)
    assert yaw_matrix(np.array([0.1, 0.2])).shape == (2, 4, 4)
    T = rigid_from(yaw_matrix(PI / 2)[:3, :3], [1, 2, 3])
    np.testing.assert_allclose(transform_points(np.array([[1.0, 0, 0]]), T), [[1, 3, 3]], atol=1e-15)
    np.testing.assert_allclose(invert_rigid(T) @ T, np.eye(4), atol=1e-15)
    assert yaw_of(T) == pytest.approx(PI / 2)


def test_transform_round_trips():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-20, 20, (100, 3)).astype(np.float32)  # float32 in, float64 out
    for yaw_only in (False, True):
        T = random_rigid(rng, yaw_only)
        moved = transform_points(pts, T)
        assert moved.dtype == np.float64
        np.testing.assert_allclose(transform_points(moved, invert_rigid(T)), pts, atol=1e-12)
        np.testing.assert_allclose(invert_rigid(T), np.linalg.inv(T), atol=1e-12)
    T = random_rigid(rng, True)
    boxes = random_boxes(rng, 20)
    back = transform_boxes(transform_boxes(boxes, T), invert_rigid(T))
    np.testing.assert_allclose(back[:, :6], boxes[:, :6], atol=1e-12)
    np.testing.assert_allclose(wrap_angle(back[:, 6] - boxes[:, 6]), 0, atol=1e-12)
    np.testing.assert_allclose(yaw_matrix(0.3) @ yaw_matrix(0.4), yaw_matrix(0.7), atol=1e-15)


def test_transform_boxes_moves_centre_and_yaw():
    T = rigid_from(yaw_matrix(PI / 2)[:3, :3], [10, 0, 1])
    out = transform_boxes(np.array([[1.0, 0, 0, 4, 2, 1, 0.25]]), T)
    np.testing.assert_allclose(out, [[10, 1, 1, 4, 2, 1, 0.25 + PI / 2]], atol=1e-12)
    out = transform_boxes(np.array([[0.0, 0, 0, 1, 1, 1, 3.0]]), yaw_matrix(1.0))
    assert out[0, 6] == pytest.approx(4.0 - 2 * PI)  # wrapped to [-pi, pi)


def test_transform_boxes_rejects_tilt():
    tilt = rigid_from(np.array([[1, 0, 0], [0, math.cos(0.1), -math.sin(0.1)], [0, math.sin(0.1), math.cos(0.1)]]))
    with pytest.raises(ValueError, match="other than z"):
        transform_boxes(np.zeros((1, 7)), tilt)
    with pytest.raises(ValueError, match="not rigid"):
        transform_boxes(np.zeros((1, 7)), np.diag([2.0, 1, 1, 1]))
    with pytest.raises(ValueError, match="not rigid"):
        transform_boxes(np.zeros((1, 7)), np.diag([1.0, -1, 1, 1]))  # a mirror is not a rotation


def test_transform_boxes_keeps_membership():
    rng = np.random.default_rng(1)
    boxes = random_boxes(rng, 15)
    near = (boxes[:, None, :3] + rng.uniform(-1.5, 1.5, (15, 200, 3))).reshape(-1, 3)  # many inside, many out
    pts = np.r_[rng.uniform(-12, 12, (1000, 3)), near]
    before = points_in_boxes(pts, boxes)
    assert 300 < before.sum() < 2500  # the check is not vacuous
    for _ in range(3):
        T = random_rigid(rng, True)
        after = points_in_boxes(transform_points(pts, T), transform_boxes(boxes, T))
        np.testing.assert_array_equal(after, before)


def test_sensor_to_camera_axes():
    # x forward → z_cam, y left → -x_cam (camera x is right), z up → -y_cam (camera y is down).
    np.testing.assert_array_equal(SENSOR_TO_CAMERA @ [1, 0, 0], [0, 0, 1])
    np.testing.assert_array_equal(SENSOR_TO_CAMERA @ [0, 1, 0], [-1, 0, 0])
    np.testing.assert_array_equal(SENSOR_TO_CAMERA @ [0, 0, 1], [0, -1, 0])
    assert np.linalg.det(SENSOR_TO_CAMERA) == 1.0
    Tr = make_tr_velo_to_cam((0.1, -0.2, 0.3))
    assert Tr.shape == (3, 4)
    np.testing.assert_array_equal(Tr, np.c_[SENSOR_TO_CAMERA, [0.1, -0.2, 0.3]])


# ----------------------------------------------------------------------------------------------------------- boxes
def test_box_corners_hand_values():
    # Heading along +y: front is +y, the right-hand side (facing +y) is +x.
    c = box_corners(np.array([[1.0, 2, 3, 4, 2, 1, PI / 2]]))[0]
    bottom = [[2, 4, 2.5], [0, 4, 2.5], [0, 0, 2.5], [2, 0, 2.5]]
    top = [[x, y, 3.5] for x, y, _ in bottom]
    np.testing.assert_allclose(c, bottom + top, atol=1e-12)
    c = box_corners(np.array([[0.0, 0, 0, 2, 1, 4, 0]], dtype=np.float32))[0]
    assert c.dtype == np.float64
    np.testing.assert_array_equal(c[:4], [[1, -0.5, -2], [1, 0.5, -2], [-1, 0.5, -2], [-1, -0.5, -2]])
    np.testing.assert_array_equal(c[4:, :2], c[:4, :2])
    assert box_corners(np.zeros((0, 7))).shape == (0, 8, 3)


def test_bev_polygons_ccw_and_match_corners():
    np.testing.assert_allclose(bev_polygons(np.array([[1.0, 2, 3, 4, 2, 1, PI / 2]]))[0],
                               [[2, 4], [0, 4], [0, 0], [2, 0]], atol=1e-12)  # fmt: skip
    boxes = random_boxes(np.random.default_rng(2), 50)
    poly = bev_polygons(boxes)
    np.testing.assert_allclose(poly, box_corners(boxes)[:, :4, :2], atol=1e-12)
    x, y = poly[..., 0], poly[..., 1]
    signed_area = 0.5 * np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1)
    np.testing.assert_allclose(signed_area, boxes[:, 3] * boxes[:, 4])  # positive: counter-clockwise
    # Corner 0 -> 1 runs across the front, from right to left; 1 -> 2 runs backwards along the heading.
    heading = np.c_[np.cos(boxes[:, 6]), np.sin(boxes[:, 6])]
    np.testing.assert_allclose(np.sum((poly[:, 1] - poly[:, 2]) * heading, axis=1), boxes[:, 3])


def _points_in_boxes_slow(points, boxes):
    out = np.zeros((len(boxes), len(points)), dtype=bool)
    for i, (x, y, z, l, w, h, yaw) in enumerate(boxes):
        R = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
        for j, p in enumerate(points):
            u, v = R.T @ (p[:2] - [x, y])
            out[i, j] = abs(u) <= l / 2 and abs(v) <= w / 2 and abs(p[2] - z) <= h / 2
    return out


def test_points_in_boxes_matches_slow_reference():
    rng = np.random.default_rng(3)
    boxes = random_boxes(rng, 12)
    pts = rng.uniform(-12, 12, (600, 3)).astype(np.float32)
    fast = points_in_boxes(pts, boxes)
    assert fast.shape == (12, 600) and fast.dtype == bool
    np.testing.assert_array_equal(fast, _points_in_boxes_slow(pts.astype(np.float64), boxes))
    assert fast.any()
    # Chunking over boxes changes nothing.
    np.testing.assert_array_equal(points_in_boxes(pts, boxes, chunk_elements=1000), fast)
    # Extra columns (reflectance) are ignored; empty inputs give empty masks.
    np.testing.assert_array_equal(points_in_boxes(np.c_[pts, np.ones(600)], boxes), fast)
    assert points_in_boxes(pts, np.zeros((0, 7))).shape == (0, 600)
    assert points_in_boxes(np.zeros((0, 3)), boxes).shape == (12, 0)


def test_points_in_boxes_faces_inclusive():
    box = np.array([[0.0, 0, 0, 2, 4, 6, 0]])
    pts = np.array([[1, 2, 3], [-1, -2, -3], [1.0000001, 0, 0], [0, 2.0000001, 0], [0, 0, -3.0000001]])
    assert points_in_boxes(pts, box)[0].tolist() == [True, True, False, False, False]


# ---------------------------------------------------------------------------------------------- camera conversions
def test_boxes_to_kitti_camera_hand_values():
    calib = simple_calib()
    loc, dims, ry, alpha = boxes_to_kitti_camera(np.array([[10.0, 2, 0.5, 4, 2, 1, 0]]), calib)
    np.testing.assert_allclose(loc, [[-2, 0, 10]], atol=1e-12)  # bottom centre: sensor z 0.5 - 0.5
    np.testing.assert_array_equal(dims, [[1, 2, 4]])  # h w l
    assert ry[0] == pytest.approx(-PI / 2)
    assert alpha[0] == pytest.approx(-PI / 2 - math.atan2(-2, 10))
    # A box heading along sensor +y (left) points along camera -x: ry = -pi (wrapped into [-pi, pi)).
    _, _, ry, _ = boxes_to_kitti_camera(np.array([[10.0, 0, 0, 4, 2, 1, PI / 2]]), calib)
    assert ry[0] == pytest.approx(-PI)


def _kitti_camera_corners(location, dims_hwl, ry):
    """Corners of KITTI camera boxes, the devkit way: rotate about camera y, y spans [y - h, y]."""
    out = []
    for (x, y, z), (h, w, l), r in zip(location, dims_hwl, ry):
        R = np.array([[math.cos(r), 0, math.sin(r)], [0, 1, 0], [-math.sin(r), 0, math.cos(r)]])
        local = np.array([[sx * l / 2, -h * sy, sz * w / 2] for sx in (-1, 1) for sy in (0, 1) for sz in (-1, 1)])
        out.append(local @ R.T + [x, y, z])
    return np.array(out)


def test_camera_conversion_is_exact_for_an_axis_swap_calib():
    rng = np.random.default_rng(4)
    calib = simple_calib(t=(0.05, -0.3, 0.1))
    boxes = random_boxes(rng, 30)
    loc, dims, ry, alpha = boxes_to_kitti_camera(boxes.astype(np.float32), calib)
    assert np.all((ry >= -PI) & (ry < PI)) and np.all((alpha >= -PI) & (alpha < PI))
    np.testing.assert_allclose(alpha, wrap_angle(ry - np.arctan2(loc[:, 0], loc[:, 2])), atol=1e-12)
    # Independent check: the sensor box's corners, moved to the camera, are the devkit's camera-box corners.
    sensor = np.array([transform_points(c, calib.velo_to_rect()) for c in box_corners(boxes.astype(np.float32))])
    camera = _kitti_camera_corners(loc, dims, ry)
    for a, b in zip(sensor, camera):
        np.testing.assert_allclose(np.array(sorted(map(tuple, a))), np.array(sorted(map(tuple, b))), atol=1e-5)
    back = kitti_camera_to_boxes(loc, dims, ry, calib)
    np.testing.assert_allclose(back[:, :6], boxes[:, :6], atol=1e-5)  # float32 input
    np.testing.assert_allclose(wrap_angle(back[:, 6] - boxes[:, 6]), 0, atol=1e-6)


# ------------------------------------------------------------------------------------------------------ projection
def test_project_box_inside_and_truncated():
    calib, size = simple_calib(), (200, 100)
    boxes = np.array([[10.0, 0, 0, 2, 2, 2, 0], [10.0, -10, 0, 2, 2, 2, 0]])
    bbox, trunc = project_boxes_to_image(boxes, calib, size)
    # Box 0: camera x, y in [-1, 1], z in [9, 11]; the extremes come from the near face z = 9.
    np.testing.assert_allclose(bbox[0], [100 - 100 / 9, 50 - 100 / 9, 100 + 100 / 9, 50 + 100 / 9])
    assert trunc[0] == 0.0
    # Box 1: camera x in [9, 11]; u in [100 + 900/11, 100 + 1100/9], clipped at W - 1 = 199.
    u0, u1 = 100 + 900 / 11, 100 + 1100 / 9
    np.testing.assert_allclose(bbox[1], [u0, 50 - 100 / 9, 199, 50 + 100 / 9])
    assert trunc[1] == pytest.approx(1 - (199 - u0) / (u1 - u0))


def test_project_box_straddling_the_camera_plane_is_clipped_at_the_near_plane():
    calib, size = simple_calib(), (200, 100)
    # Camera x in [2, 4], y in [-1, 1], z in [-1, 3]: the visible part (z > 0) lies right of u = 100 + 100 * 2/3.
    box = np.array([[1.0, -3, 0, 4, 2, 2, 0]])
    bbox, trunc = project_boxes_to_image(box, calib, size)
    np.testing.assert_allclose(bbox[0], [100 + 200 / 3, 0, 199, 99])
    assert 0.99 < trunc[0] < 1.0
    # Projecting the 8 corners without clipping would have put the left edge off the left of the image.
    uvw = np.c_[box_corners(box)[0], np.ones(8)] @ calib.velo_to_image().T
    assert (uvw[:, 0] / uvw[:, 2]).min() < 0


def test_project_box_behind_or_outside():
    calib, size = simple_calib(), (200, 100)
    boxes = np.array([[-10.0, 0, 0, 2, 2, 2, 0], [10.0, -50, 0, 2, 2, 2, 0], [10.0, 0, 0, 2, 2, 2, 0]])
    bbox, trunc = project_boxes_to_image(boxes, calib, size)
    np.testing.assert_array_equal(bbox[0], [0, 0, 0, 0])
    assert trunc.tolist()[:2] == [1.0, 1.0] and trunc[2] == 0.0
    assert bbox[1, 0] == bbox[1, 2] == 199  # squashed onto the right border
    assert project_boxes_to_image(np.zeros((0, 7)), calib, size)[0].shape == (0, 4)


def test_fov_mask_hand_values():
    calib = simple_calib()
    # A sensor point (x, y, z) in front lands at u = 100 - 100 y / x, v = 50 - 100 z / x; inside: u < 200, v < 100.
    pts = np.array([[10, 0, 0], [10, -15, 0], [-10, 0, 0], [10, -9.9, 0], [10, -10, 0], [10, 10, 0], [10, 0, 5],
                    [10, 0, 5.1]])  # fmt: skip
    assert fov_mask(pts, calib, (200, 100)).tolist() == [True, False, False, True, False, True, True, False]


# --------------------------------------------------------------------------------------------------------- pillars
def test_pillar_coords_hand_values_and_half_open_boundary():
    pc_range, voxel = (0.0, -1.0, -1.0, 2.0, 1.0, 1.0), (0.5, 0.5, 2.0)
    assert grid_size(pc_range, voxel) == (4, 4)
    pts = np.array([
        [0.0, -1.0, -1.0],    # the min corner: kept, pillar (0, 0)
        [2.0, 0.0, 0.0],      # x == x_max: dropped
        [1.999, 0.999, 0.999],  # just inside the max corner: (3, 3)
        [0.5, 0.0, 0.0],      # on a pillar boundary: the upper pillar, iy 2, ix 1
        [0.49, -0.51, 0.0],   # (0, 0)
        [1.0, 0.0, 1.0],      # z == z_max: dropped
        [1.0, 0.0, -1.0],     # z == z_min: kept, (2, 2)
        [-0.001, 0.0, 0.0],   # x < x_min: dropped
        [1.0, 1.0, 0.0],      # y == y_max: dropped
    ])  # fmt: skip
    coords, keep = pillar_coords(pts, pc_range, voxel)
    assert keep.tolist() == [True, False, True, True, True, False, True, False, False]
    assert coords.dtype == np.int64
    assert coords.tolist() == [[0, 0], [3, 3], [2, 1], [0, 0], [2, 2]]  # [iy, ix], in point order
    c32, k32 = pillar_coords(pts.astype(np.float32), pc_range, voxel[:2])
    np.testing.assert_array_equal(k32, keep)
    np.testing.assert_array_equal(c32, coords)


def test_pillar_coords_kitti_range_float32_edges():
    pc_range, voxel = (0, -39.68, -3, 69.12, 39.68, 1), (0.16, 0.16, 4)
    assert grid_size(pc_range, voxel) == (432, 496)
    below = np.nextafter(np.float32(69.12), np.float32(0))  # largest float32 below the max
    pts = np.array([[np.float32(69.12), 0, 0], [below, 0, 0], [0, -39.68, -3]], dtype=np.float32)
    coords, keep = pillar_coords(pts, pc_range, voxel)
    # float32(69.12) is 69.1200027... >= 69.12, so it is out; float32(-39.68) is -39.6800003... < -39.68, out too.
    assert keep.tolist() == [False, True, False]
    assert coords.tolist() == [[248, 431]]


def test_pillar_coords_matches_per_point_floor():
    rng = np.random.default_rng(5)
    pc_range, voxel = (-4.0, -3.2, -1.0, 4.0, 3.2, 2.0), (0.16, 0.16)
    pts = rng.uniform(-5, 5, (3000, 4)).astype(np.float32)
    coords, keep = pillar_coords(pts, pc_range, voxel)
    expected_keep, expected = [], []
    for x, y, z, _ in pts.astype(np.float64):
        ok = -4 <= x < 4 and -3.2 <= y < 3.2 and -1 <= z < 2
        expected_keep.append(ok)
        if ok:
            expected.append([math.floor((y + 3.2) / 0.16), math.floor((x + 4.0) / 0.16)])
    assert keep.tolist() == expected_keep
    assert coords.tolist() == expected
    assert coords[:, 0].max() < 40 and coords[:, 1].max() < 50 and coords.min() >= 0


def test_pillar_range_must_be_whole_voxels():
    with pytest.raises(ValueError, match="whole number"):
        grid_size((0, 0, 0, 1.0, 1.0, 1), (0.3, 0.3))
    with pytest.raises(ValueError, match="min < max"):
        pillar_coords(np.zeros((1, 3)), (0, 0, 1, 1, 1, 1), (0.5, 0.5))
