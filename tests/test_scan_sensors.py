"""Sensor profiles: the paper's ray pattern, planar depth, calibration and the shipped profiles."""

from __future__ import annotations

import numpy as np
import pytest

from mpchair.core.errors import InputError
from mpchair.geometry import SENSOR_TO_CAMERA
from mpchair.scan.sensors import (
    available_sensors,
    camera_calib,
    grid_directions,
    grid_pixels_of,
    load_sensor,
    scan_directions,
)


def test_paper_pattern_has_21095_rays_in_habitat_order():
    s = load_sensor("mp3d-depth90")
    d = scan_directions(s)
    assert d.shape == (21095, 3)
    # Row-major over rows 0, 10, ..., 1020, every 5th ray: the k-th line starts at column (k * 4) mod 5 offset.
    rows, cols = grid_pixels_of(s.camera, d)
    rows, cols = np.rint(rows).astype(int), np.rint(cols).astype(int)
    flat = rows // 10 * 1024 + cols
    np.testing.assert_array_equal(flat, np.arange(0, 103 * 1024, 5))
    assert set(np.unique(rows)) == set(range(0, 1021, 10))
    # u = -1 + 2c/1023 (left to right), v = 1 - 2r/1023; our y = -u (left), z = v (up), x = 1 (planar depth).
    np.testing.assert_allclose(d[0], [1.0, 1.0, 1.0])
    np.testing.assert_allclose(grid_directions(s.camera, [1023], [1023])[0], [1.0, -1.0, -1.0])
    assert s.max_range == 25.0 and s.range_mode == "planar" and (s.z_min, s.z_max) == (-2.0, 2.0)


def test_calib_is_the_virtual_camera_with_a_real_axis_swap():
    s = load_sensor("mp3d-depth90")
    c = camera_calib(s.camera)
    np.testing.assert_allclose(c.P2, [[512, 0, 512, 0], [0, 512, 512, 0], [0, 0, 1, 0]])
    np.testing.assert_array_equal(c.R0_rect, np.eye(3))
    np.testing.assert_array_equal(c.Tr_velo_to_cam[:, :3], SENSOR_TO_CAMERA)
    assert np.linalg.det(c.Tr_velo_to_cam[:, :3]) == pytest.approx(1.0)
    # A point straight ahead lands on the principal point; one 45 deg to the left on the left image edge.
    uvw = c.velo_to_image() @ np.array([[2.0, 0, 0, 1], [2.0, 2.0, 0, 1]]).T
    np.testing.assert_allclose((uvw[:2] / uvw[2]).T, [[512, 512], [0, 512]], atol=1e-9)


def test_spinning_profiles_are_360_degrees():
    assert {"mp3d-depth90", "lidar64", "lidar16"} <= set(available_sensors())
    for name, n in (("lidar64", 64 * 1024), ("lidar16", 16 * 1800)):
        s = load_sensor(name)
        d = scan_directions(s)
        assert d.shape == (n, 3)
        np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
        az = np.arctan2(d[:, 1], d[:, 0])
        assert az.min() < -3.1 and az.max() > 3.1  # all around
        el = np.degrees(np.arcsin(d[:, 2]))
        lo, hi = s.spinning.elevation_min_deg, s.spinning.elevation_max_deg
        assert el.min() == pytest.approx(lo) and el.max() == pytest.approx(hi)
        assert s.filters.min_scan_points > 0


def test_unknown_sensor_lists_the_available_ones(tmp_path):
    with pytest.raises(InputError, match="available: .*mp3d-depth90"):
        load_sensor("kinect")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\ndescription: y\npattern: pinhole\nrange_mode: planar\nmax_range: 5\ncamera: {}\n")
    with pytest.raises(InputError, match="bad.yaml.*pinhole"):
        load_sensor(bad)


def test_mask_rays_equal_the_rotated_grid_directions_in_float32():
    from mpchair.geometry import rotate_vectors
    from mpchair.scan.grid_rays import mask_rays

    cam = load_sensor("mp3d-depth90").camera
    rng = np.random.default_rng(3)
    mask = np.zeros((cam.height, cam.width), dtype=bool)
    mask[100:140:3, 700:900] = True
    mask[rng.integers(0, cam.height, 500), rng.integers(0, cam.width, 500)] = True
    a = rng.uniform(0, 2 * np.pi)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    pixels, dw = mask_rays(mask, cam, R)
    er, ec = np.nonzero(mask)  # row-major, like the kernel
    np.testing.assert_array_equal(pixels, er * cam.width + ec)
    assert dw.dtype == np.float32
    np.testing.assert_array_equal(dw, rotate_vectors(grid_directions(cam, er, ec), R).astype(np.float32))
    empty = mask_rays(np.zeros_like(mask), cam, R)
    assert [len(x) for x in empty] == [0, 0]
    with pytest.raises(ValueError, match="camera grid"):
        mask_rays(mask[:10], cam, R)
