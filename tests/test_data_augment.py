"""GT database + sampling and the augmentations of detector.data, on the tiny synthetic KITTI-format dataset."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
from helpers_detector import make_tiny_dataset

from detector.data import (
    AugmentOptions,
    GTDatabase,
    KittiDataset,
    bev_boxes_overlap,
    build_gt_database,
    global_rotation,
    global_scaling,
    make_training_sample,
    random_flip_y,
    sample_ground_truth,
    sample_rng,
)
from detector.data.pipeline import TrainingSet
from mpchair.core.errors import InputError
from mpchair.geometry import bev_polygons, points_in_boxes

RANGE = (0.0, -6.4, -1.0, 12.8, 6.4, 2.0)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = make_tiny_dataset(tmp_path_factory.mktemp("tiny"), n_frames=6, seed=3)
    return KittiDataset(root, "train", classes=("Chair",), fov_crop=False)


@pytest.fixture(scope="module")
def database(dataset):
    return build_gt_database(dataset)


def _shapely_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    pa, pb = shapely.Polygon(bev_polygons(a[None])[0]), shapely.Polygon(bev_polygons(b[None])[0])
    return pa.intersection(pb).area > 1e-9


def test_bev_overlap_matches_shapely():
    rng = np.random.default_rng(1)
    boxes = np.column_stack([rng.uniform(0, 4, (60, 2)), np.zeros(60), rng.uniform(0.3, 2, (60, 3)),
                             rng.uniform(-math.pi, math.pi, 60)])
    got = bev_boxes_overlap(boxes, boxes)
    polys = shapely.polygons(bev_polygons(boxes))
    want = shapely.area(shapely.intersection(polys[:, None], polys[None])) > 1e-9
    np.testing.assert_array_equal(got, want)
    assert 0 < want.mean() < 1  # both outcomes are exercised


def test_database_holds_every_chair_with_its_points(dataset, database):
    n_chairs = sum(len(f.boxes) for f in dataset)
    assert len(database) == n_chairs and set(database.names) == {"Chair"}
    for e in range(len(database)):
        pts = database.object_points(e)
        assert len(pts) >= 150  # the builder puts 150-250 points on each chair (plus floor points under it)
        assert points_in_boxes(pts, database.boxes[e][None]).all()


def test_database_save_load_roundtrip(tmp_path, database):
    database.save(tmp_path / "db.npz")
    loaded = GTDatabase.load(tmp_path / "db.npz")
    np.testing.assert_array_equal(loaded.points, database.points)
    np.testing.assert_array_equal(loaded.boxes, database.boxes)
    assert loaded.names.tolist() == database.names.tolist()
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="cannot read GT database"):
        GTDatabase.load(tmp_path / "bad.npz")


def test_gt_sampling_pastes_without_collisions(dataset, database):
    frame = dataset[0]
    total_pasted = 0
    for seed in range(5):
        out = sample_ground_truth(frame.points, frame.boxes, frame.labels, database=database, classes=("Chair",),
                                  sample_counts={"Chair": 12}, min_points={"Chair": 5},
                                  rng=np.random.default_rng(seed), obstacles=frame.other_boxes)
        n_scene = len(frame.boxes)
        assert out.num_pasted > 0 and len(out.boxes) == n_scene + out.num_pasted <= 12
        np.testing.assert_array_equal(out.boxes[:n_scene], frame.boxes)
        everything = np.concatenate([out.boxes, frame.other_boxes])
        for i in range(len(everything)):  # no two boxes (scene, obstacle or pasted) share BEV area (shapely oracle)
            for j in range(i + 1, len(everything)):
                assert not _shapely_overlap(everything[i], everything[j])
        # Each pasted box holds exactly the database points of the object pasted there: no scene point survives in it.
        pasted = out.boxes[n_scene:]
        inside = points_in_boxes(out.points, pasted)
        for k, box in enumerate(pasted):
            e = int(np.flatnonzero(np.all(database.boxes == box, axis=1))[0])
            assert inside[k].sum() == database.num_points[e]
        total_pasted += out.num_pasted
    assert total_pasted >= 5


def test_gt_sampling_is_deterministic_for_a_seed(dataset, database):
    frame = dataset[1]
    kwargs = dict(database=database, classes=("Chair",), sample_counts={"Chair": 10}, min_points={"Chair": 0})
    a = sample_ground_truth(frame.points, frame.boxes, frame.labels, rng=np.random.default_rng(7), **kwargs)
    b = sample_ground_truth(frame.points, frame.boxes, frame.labels, rng=np.random.default_rng(7), **kwargs)
    c = sample_ground_truth(frame.points, frame.boxes, frame.labels, rng=np.random.default_rng(8), **kwargs)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.boxes, b.boxes)
    assert not np.array_equal(a.boxes, c.boxes)
    # min_points above every object's count leaves nothing to paste.
    none = sample_ground_truth(frame.points, frame.boxes, frame.labels, rng=np.random.default_rng(7),
                               **{**kwargs, "min_points": {"Chair": 10_000}})
    assert none.num_pasted == 0 and none.points is frame.points


def _membership_kept(points_before, boxes_before, points_after, boxes_after):
    """Points well inside a box stay inside it; points well outside stay outside (1 mm margin for float rounding)."""
    shrunk, grown = boxes_before.copy(), boxes_before.copy()
    shrunk[:, 3:6] -= 2e-3
    grown[:, 3:6] += 2e-3
    after = points_in_boxes(points_after, boxes_after)
    assert np.all(after[points_in_boxes(points_before, shrunk)])
    assert not np.any(after[~points_in_boxes(points_before, grown)])
    assert after.sum() > 0


@pytest.mark.parametrize("which", ["flip", "rotation", "scaling"])
def test_global_augmentations_keep_points_in_their_boxes(dataset, which):
    frame = dataset[2]
    rng = np.random.default_rng(0)
    if which == "flip":
        points, boxes, flipped = random_flip_y(frame.points, frame.boxes, rng, probability=1.0)
        assert flipped and np.allclose(points[:, 1], -frame.points[:, 1])
    elif which == "rotation":
        points, boxes = global_rotation(frame.points, frame.boxes, 0.7)
        np.testing.assert_allclose(np.hypot(points[:, 0], points[:, 1]), np.hypot(*frame.points[:, :2].T), rtol=1e-5)
    else:
        points, boxes = global_scaling(frame.points, frame.boxes, 1.07)
        np.testing.assert_allclose(boxes[:, 3:6], frame.boxes[:, 3:6] * 1.07)
    _membership_kept(frame.points, frame.boxes, points, boxes)
    np.testing.assert_array_equal(points[:, 3], frame.points[:, 3])  # reflectance rides along


def test_training_sample_is_a_function_of_seed_epoch_index(dataset, database):
    options = AugmentOptions(point_cloud_range=RANGE, num_point_features=3, gt_sampling=True,
                             sample_counts=(("Chair", 8),), min_points=(("Chair", 5),), flip=True,
                             rotation=(-0.3, 0.3), scaling=(0.95, 1.05))
    ts = TrainingSet(dataset, options, seed=11, database=database)
    a, b, c = ts[(0, 3)], ts[(0, 3)], ts[(1, 3)]
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.boxes, b.boxes)
    assert not np.array_equal(a.points, c.points)
    direct = make_training_sample(dataset[3], options, sample_rng(11, 0, 3), database, ("Chair",))
    np.testing.assert_array_equal(direct.points, a.points)
    assert a.points.shape[1] == 3 and a.points.dtype == np.float32
    lo, hi = np.array(RANGE[:3]), np.array(RANGE[3:])
    assert np.all((a.points >= lo) & (a.points < hi))
    assert np.all((a.boxes[:, 0] >= RANGE[0]) & (a.boxes[:, 0] <= RANGE[3]))
    # GT sampling added chairs to some scenes (others are too full to take a pasted chair without a collision).
    assert any(len(ts[(0, k)].boxes) > len(dataset[k].boxes) for k in range(len(dataset)))


def test_shuffle_and_range_filter_switches(dataset):
    frame = dataset[0]
    plain = AugmentOptions(point_cloud_range=RANGE, shuffle=False, range_filter=False)
    out = make_training_sample(frame, plain, sample_rng(0, 0, 0))
    np.testing.assert_array_equal(out.points, frame.points)  # everything off → the frame as read
    narrow = AugmentOptions(point_cloud_range=(0.0, -2.0, -1.0, 6.0, 2.0, 2.0), shuffle=True)
    out = make_training_sample(frame, narrow, sample_rng(0, 0, 0))
    assert len(out.points) < len(frame.points)
    assert np.all((out.boxes[:, 0] <= 6.0) & (np.abs(out.boxes[:, 1]) <= 2.0))
