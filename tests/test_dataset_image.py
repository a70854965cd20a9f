"""image_2: the compiled depth projection equals the numpy one, and our PNG encoder is a valid, exact PNG."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from mpchair.dataset.image import depth_image, depth_image_reference, png_bytes
from mpchair.scan.sensors import camera_calib, load_sensor


def test_depth_image_equals_the_numpy_reference_and_keeps_the_nearest_point():
    cam = load_sensor("mp3d-depth90").camera
    calib = camera_calib(cam)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-3, 20, 20000), rng.uniform(-20, 20, 20000), rng.uniform(-3, 3, 20000),
                           np.ones(20000)]).astype(np.float32)
    # Two points on the same ray: the nearer (brighter) one wins whatever the order.
    pts[:2, :3] = [[10.0, 0.0, 0.0], [2.0, 0.0, 0.0]]
    img = depth_image(pts, calib, (cam.width, cam.height), 25.0)
    assert img.dtype == np.uint8 and img.shape == (1024, 1024)
    np.testing.assert_array_equal(img, depth_image_reference(pts, calib, (cam.width, cam.height), 25.0))
    assert img[512, 512] == 1 + round(254 * (1 - 2.0 / 25.0))
    assert (img > 0).sum() > 1000  # points behind the camera (x < 0) and outside the image are not drawn
    assert not depth_image(pts[:0], calib, (cam.width, cam.height), 25.0).any()


@pytest.mark.parametrize("shape", [(1, 1), (7, 13), (1024, 1024)])
def test_png_bytes_decode_to_the_same_pixels(shape):
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, shape, dtype=np.uint8)
    img[rng.random(shape) < 0.8] = 0  # mostly empty, like a projected scan
    data = png_bytes(img)
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    back = Image.open(io.BytesIO(data))
    assert back.mode == "L" and back.size == (shape[1], shape[0])
    np.testing.assert_array_equal(np.asarray(back), img)
    assert png_bytes(img) == data  # deterministic


def test_png_bytes_rejects_other_images():
    with pytest.raises(ValueError, match="uint8"):
        png_bytes(np.zeros((4, 4), dtype=np.float32))
    with pytest.raises(ValueError, match=r"\(H,W\)"):
        png_bytes(np.zeros((4, 4, 3), dtype=np.uint8))


def test_png_bytes_with_runs_of_empty_rows_like_a_scan():
    img = np.zeros((1024, 1024), dtype=np.uint8)
    img[::10, ::5] = np.random.default_rng(2).integers(1, 256, (103, 205), dtype=np.uint8)
    img[500:530] = 9  # a run of full rows
    for a in (img, np.zeros_like(img), np.full_like(img, 3), img[:, :1000]):
        data = png_bytes(np.ascontiguousarray(a))
        np.testing.assert_array_equal(np.asarray(Image.open(io.BytesIO(data))), a)
    assert len(png_bytes(img)) < 100_000  # compressed, not stored
