"""Open3D-ML reads an mpchair dataset through ``mpchair.kitti.open3d_ml``: its own KITTI label/calib parsing gives the
same 3D boxes as ours, and the full scans (not KITTI's 375 x 1242 crop) come through."""

from __future__ import annotations

import numpy as np
import pytest

from mpchair.core.errors import InputError
from mpchair.dataset.generate import GenerateRequest, generate
from mpchair.geometry import box_corners, labels_to_boxes
from mpchair.kitti import frame_paths, read_calib, read_imageset, read_labels, read_velodyne
from mpchair.kitti.open3d_ml import open3d_ml_dataset
from mpchair.synth import synthesize_house, write_house

pytest.importorskip("open3d.ml.datasets", reason="Open3D-ML (the project's open3d extra) is not installed")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("houses")
    house = synthesize_house(3, levels=1)
    write_house(root, house)
    out = tmp_path_factory.mktemp("ds") / "ds"
    generate(GenerateRequest(root=root, houses=(house.id,), frames=6, out=out, seed=2, progress=False))
    return out


def test_open3d_ml_reads_our_boxes_and_full_scans(dataset, monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)  # Open3D-ML may create its ./logs cache folder
    ds = open3d_ml_dataset(dataset)
    train_ids = read_imageset(dataset / "ImageSets" / "train.txt")
    assert ds.get_split_list("train") == [str(frame_paths(dataset, i).velodyne) for i in train_ids]
    boxes_seen = 0
    for split in ("train", "val", "test"):
        sp = ds.get_split(split)
        for k in range(len(sp)):
            data = sp.get_data(k)
            fid = sp.get_attr(k)["name"]
            paths = frame_paths(dataset, fid)
            points = read_velodyne(paths.velodyne)
            # The whole scan, not KITTI's fixed window (which would drop most of a 1024 x 1024 camera's points).
            np.testing.assert_array_equal(data["point"], points)
            labels = read_labels(paths.label_2)
            calib = read_calib(paths.calib)
            ours = labels_to_boxes(labels.objects(), calib)
            theirs = data["bounding_boxes"]
            assert [b.label_class for b in theirs] == list(labels.objects().names) == ["Chair"] * len(ours)
            # Same boxes: Open3D-ML's corners (rectified camera frame) equal ours moved into that frame.
            T = calib.velo_to_rect()
            for box, obj in zip(ours, theirs):
                c = box_corners(box[None])[0]
                cam = c @ T[:3, :3].T + T[:3, 3]
                got = obj.generate_corners3d()
                # The same 8 points in any order: every corner has a partner within 2 mm, both ways (sorting each
                # axis separately would not see a mirrored yaw).
                dist = np.linalg.norm(got[:, None, :] - cam[None, :, :], axis=-1)
                assert dist.shape == (8, 8) and dist.min(axis=0).max() < 2e-3 and dist.min(axis=1).max() < 2e-3
            boxes_seen += len(ours)
    assert boxes_seen >= 6


def test_not_a_dataset_is_a_clear_error(tmp_path):
    with pytest.raises(InputError, match="no training/velodyne"):
        open3d_ml_dataset(tmp_path)
