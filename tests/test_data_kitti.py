"""detector.data.kitti_dataset on the vendored real KITTI frames (tests/data/kitti) and on bad input."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from detector.data import KittiDataset, load_frame
from mpchair.core.errors import InputError
from mpchair.geometry import fov_mask, points_in_boxes
from mpchair.kitti import frame_paths, read_calib, read_velodyne, write_velodyne

ROOT = Path(__file__).parent / "data" / "kitti"
KITTI_CLASSES = ("Car", "Pedestrian", "Cyclist", "Truck", "Misc")
# Points of the vendored scans inside each labelled (non-DontCare) box, in label-file order: every box holds points.
EXPECTED_COUNTS = {
    "000000": [377],
    "000001": [71, 9, 18],
    "000002": [1349, 67],
    "000003": [674],
    "000004": [78, 26],
    "000005": [70],
}


def test_labels_become_sensor_boxes_that_contain_their_points():
    ds = KittiDataset(ROOT, "train", classes=KITTI_CLASSES, fov_crop=True)
    assert ds.ids == sorted(EXPECTED_COUNTS)
    for frame in ds:
        counts = points_in_boxes(frame.points, frame.boxes).sum(1).tolist()
        assert counts == EXPECTED_COUNTS[frame.frame_id], frame.frame_id
        # Sensor frame: objects are in front of the LiDAR (x forward) and stand on the road, which lies 0.8-2.1 m
        # below it (mounted 1.73 m up; the road slopes): z is up and the box centre is h/2 above its bottom.
        assert np.all(frame.boxes[:, 0] > 0)
        bottom = frame.boxes[:, 2] - frame.boxes[:, 5] / 2
        assert np.all((bottom > -2.1) & (bottom < -0.8)), (frame.frame_id, bottom)
        assert frame.points.dtype == np.float32 and frame.points.shape[1] == 4


def test_frame_000001_classes_dontcare_and_name_map():
    frame = load_frame(ROOT, "000001", classes=("Car",), fov_crop=False)
    assert frame.names.tolist() == ["Car"] and frame.labels.tolist() == [0]
    np.testing.assert_allclose(frame.boxes[0, 3:6], [3.69, 1.87, 1.67])  # l, w, h from "h w l" = 1.67 1.87 3.69
    # DontCare rows are kept for evaluation but never become training boxes.
    assert frame.gt.names.tolist() == ["Truck", "Car", "Cyclist"] + ["DontCare"] * 4
    assert len(frame.other_boxes) == 2  # Truck and Cyclist: obstacles for GT sampling, not targets
    mapped = load_frame(ROOT, "000001", classes=("Car", "Bike"), name_map={"Cyclist": "Bike"}, fov_crop=False)
    assert mapped.names.tolist() == ["Car", "Bike"] and mapped.labels.tolist() == [0, 1]
    assert mapped.gt.names.tolist()[2] == "Cyclist"  # evaluation keeps the file's own names


def test_fov_crop_uses_each_frames_image_size(tmp_path):
    """The crop keeps exactly the points inside this frame's image_2 (tests/test_kitti_real.py shows the vendored scans
    are that set): points behind the camera, beside it, or inside a 1242 x 375 image but outside frame 000000's
    1224 x 370 one are dropped."""
    root = tmp_path / "kitti"
    shutil.copytree(ROOT, root)
    rng = np.random.default_rng(0)
    for fid in EXPECTED_COUNTS:
        path = frame_paths(root, fid).velodyne
        scan = read_velodyne(path)
        behind = scan.copy()
        behind[:, 0] = -behind[:, 0] - 1.0  # behind the camera: projects "into" the image, but z_cam < 0
        side = scan[rng.choice(len(scan), 500)].copy()
        side[:, :2] = side[:, [1, 0]] * [-1, 1]  # rotated 90 deg: far outside the horizontal field of view
        extra = [behind, side]
        if fid == "000000":  # the odd image size: add points that only a fixed 1242 x 375 crop would keep
            calib = read_calib(frame_paths(root, fid).calib)
            cand = np.c_[rng.uniform([4, -25, -2], [40, 25, 2], size=(200_000, 3)), np.ones(200_000)]
            border = cand[fov_mask(cand, calib, (1242, 375)) & ~fov_mask(cand, calib, (1224, 370))]
            assert len(border) > 100
            extra.append(border.astype(np.float32))
        write_velodyne(path, np.concatenate([scan, *extra]))
        frame = load_frame(root, fid, classes=KITTI_CLASSES, fov_crop=True)
        np.testing.assert_array_equal(frame.points, scan)


def test_bad_input_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="dataset folder not found"):
        KittiDataset(tmp_path / "nope", "train", classes=("Car",))
    root = tmp_path / "kitti"
    shutil.copytree(ROOT, root)
    with pytest.raises(InputError, match="image set file not found"):
        KittiDataset(root, "test", classes=("Car",))
    frame_paths(root, "000003").image_2.unlink()
    with pytest.raises(InputError, match="image file not found"):
        load_frame(root, "000003", classes=("Car",), fov_crop=True)
    assert len(load_frame(root, "000003", classes=("Car",), fov_crop=False).boxes) == 1  # no crop → no image needed
    frame_paths(root, "000004").velodyne.write_bytes(b"\0" * 10)
    with pytest.raises(InputError, match="multiple of 16"):
        load_frame(root, "000004", classes=("Car",))
