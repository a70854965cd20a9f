"""detector.data.kitti_dataset on the vendored real KITTI frames (tests/data/kitti) and on bad input."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from detector.data import KittiDataset, load_frame
from mpchair.errors import InputError
from mpchair.geometry import points_in_boxes
from mpchair.kitti import frame_paths, read_velodyne, write_velodyne

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
        # Sensor frame: objects are in front of the LiDAR (x forward) and centred above the road (z up, ~-1 m).
        assert np.all(frame.boxes[:, 0] > 0)
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


def test_fov_crop_uses_each_frames_image_size_and_keeps_box_points(tmp_path):
    root = tmp_path / "kitti"
    shutil.copytree(ROOT, root)
    rng = np.random.default_rng(0)
    for fid, counts in EXPECTED_COUNTS.items():
        path = frame_paths(root, fid).velodyne
        scan = read_velodyne(path)
        behind = scan.copy()
        behind[:, 0] = -behind[:, 0] - 1.0  # behind the camera: projects "into" the image, but z_cam < 0
        side = scan[rng.choice(len(scan), 500)].copy()
        side[:, :2] = side[:, [1, 0]] * [-1, 1]  # rotated 90 deg: far outside the horizontal field of view
        write_velodyne(path, np.concatenate([scan, behind, side]))
        frame = load_frame(root, fid, classes=KITTI_CLASSES, fov_crop=True)
        # The vendored scans are FOV crops already: the crop must return exactly them, and every box keeps its points.
        np.testing.assert_array_equal(frame.points, scan)
        assert points_in_boxes(frame.points, frame.boxes).sum(1).tolist() == counts
        W, H = frame.image_size
        uv = frame.calib.rect_to_image((frame.calib.velo_to_rect() @ np.c_[frame.points[:, :3], np.ones(len(scan))].T)
                                       .T[:, :3])
        assert uv[:, 0].min() >= 0 and uv[:, 0].max() < W and uv[:, 1].min() >= 0 and uv[:, 1].max() < H
    assert load_frame(root, "000000", classes=KITTI_CLASSES).image_size == (1224, 370)


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
