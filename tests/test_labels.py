"""Labels on hand-made scenes: boxes through the pose, and each filter on a constructed case."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers_scenes import WALL, HouseBuilder

from mpchair.dataset.frame import cast_scan
from mpchair.geometry import box_corners, canonical_yaw, points_in_boxes, transform_boxes, transform_points
from mpchair.labels import ObjectScenes, boxes_to_sensor, decide_boxes
from mpchair.labels.visibility import covering_boxes, outside_vertices
from mpchair.scan.raycast import make_raycaster
from mpchair.scan.sensors import camera_calib, load_sensor, scan_directions

OFFSET = np.array([-3210.0, 4567.0, 8.0])
SENSOR = load_sensor("mp3d-depth90")


def _pose(x, y, yaw, height=1.0):
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = OFFSET + [x, y, height]
    return T


def _decide(house, pose, filters=SENSOR.filters, coarse=True, rc=None):
    """Decisions as `mpchair generate` makes them (coarse first stage) or, with ``coarse=False``, on every pixel."""
    objs = np.array([i for i, o in enumerate(house.objects) if o.mpcat40_index == 3])
    boxes = np.stack([house.objects[i].aligned_box for i in objs])
    rc = rc or make_raycaster(house.vertices, house.faces)
    scenes = ObjectScenes(house.vertices, house.faces, house.face_object)
    cover = covering_boxes(house.vertices, house.faces, house.face_object, objs, boxes)
    outside = outside_vertices(house.vertices, house.faces, house.face_object, objs, boxes, filters.box_margin)
    dec = decide_boxes(boxes, objs, pose, rc, house.face_object, SENSOR.camera, camera_calib(SENSOR.camera), filters,
                       scenes, cover, outside, coarse_rays=4096 if coarse else None)
    return dec, rc


def test_boxes_follow_the_pose_and_scan_points_inside_are_the_chair():
    hb = HouseBuilder()
    hb.room(0, 0, 8, 6)
    a = hb.chair(3.0, 2.5, 0.3)
    b = hb.chair(4.0, 4.2, -1.1, size=(0.6, 0.5, 1.0))
    house = hb.build(offset=OFFSET)
    pose = _pose(1.0, 3.0, 0.2)
    dec, rc = _decide(house, pose)
    assert dec.reasons == ("", "")
    # Construction: chair a at world (3, 2.5), yaw 0.3; the sensor at (1, 3, 1) with yaw 0.2.
    for k, (x, y, yaw, size) in zip((a, b), ((3.0, 2.5, 0.3, (0.5, 0.45, 0.9)), (4.0, 4.2, -1.1, (0.6, 0.5, 1.0)))):
        c, s = np.cos(-0.2), np.sin(-0.2)
        dx, dy = x - 1.0, y - 3.0
        expect = [c * dx - s * dy, s * dx + c * dy, size[2] / 2 - 1.0, *size, canonical_yaw(yaw - 0.2)]
        np.testing.assert_allclose(dec.boxes[list(dec.objects).index(k)], expect, atol=1e-9)
    assert (dec.visible_pixels > 35).all() and (dec.in_box_fraction >= 0.99).all()
    assert set(dec.occluded) <= {0, 1, 2}
    # Scan points inside a kept box (above the floor) are hits on that chair, and there are plenty.
    d = scan_directions(SENSOR)
    pts = cast_scan(SENSOR, d, pose, rc)
    _, face = rc.cast(pose[:3, 3], d @ pose[:3, :3].T)
    for k in (a, b):
        j = list(dec.objects).index(k)
        grown = dec.boxes[j : j + 1].copy()
        grown[0, 3:6] += 0.02
        inside = points_in_boxes(pts[:, :3], grown)[0] & (pts[:, 2] > -1.0 + 0.01)
        assert inside.sum() > 50
        # Recover each point's ray: points and ray hits are in the same order for hit rays inside the crop.
        world = transform_points(pts[inside, :3].astype(np.float64), pose)
        hit_world = pose[:3, 3] + d @ pose[:3, :3].T * rc.cast(pose[:3, 3], d @ pose[:3, :3].T)[0][:, None]
        on_chair = house.face_object[face] == k
        dist = np.min(np.linalg.norm(world[:, None] - hit_world[on_chair][None], axis=2), axis=1)
        assert dist.max() < 1e-4


def test_sensor_boxes_have_a_canonical_yaw():
    """A front-less box's yaw in the sensor frame is its long side's direction in [-pi/2, pi/2), whatever the fit's
    world yaw and the sensor's heading: same box (corner set), canonical angle."""
    world = np.array([[2.0 + 0.1 * k, 1.0, 0.45, 0.6, 0.4, 0.9, yaw] for k, yaw in
                      enumerate(np.linspace(-3 * np.pi, 3 * np.pi, 41))])
    for sensor_yaw in (0.0, 2.0, -2.9, np.pi / 2):
        pose = _pose(0.5, -0.5, sensor_yaw)
        out = boxes_to_sensor(world, pose)
        assert ((out[:, 6] >= -np.pi / 2) & (out[:, 6] < np.pi / 2)).all()
        plain = transform_boxes(world, np.linalg.inv(pose))
        assert (np.abs(out[:, 6] - plain[:, 6]) > 1).any()  # some yaws really were turned by pi
        # The same physical box: corner sets match (a pi turn only permutes the corners).
        a, b = box_corners(out), box_corners(plain)
        for ca, cb in zip(a, b):
            d = np.linalg.norm(ca[:, None] - cb[None], axis=2)
            assert d.min(axis=1).max() < 1e-9
        np.testing.assert_allclose(out[:, :6], plain[:, :6], atol=1e-12)


def test_filters_on_constructed_cases():
    hb = HouseBuilder()
    hb.room(0, 0, 12, 8)
    near = hb.chair(3.0, 3.0)  # kept
    far = hb.chair(9.6, 3.0)  # 8.6 m away: distance
    hidden = hb.chair(5.5, 6.0)  # 5.4 m away, 34 deg left, behind a wall: visible pixels
    hb.add_box((4.5, 5.0, 1.3), (5.0, 0.1, 2.6), category=WALL)
    side = hb.chair(1.2, 5.0)  # 90 deg to the left: fov
    high = hb.add_box((5.0, 2.4, 2.3), (0.5, 0.45, 0.5), category=3)  # a "chair" 1.3 m above the sensor: height
    high = sum(1 for p in hb.parts[: high + 1] if p[2] >= 0) - 1
    holey = hb.chair(4.5, 1.6)  # its label leaks onto a big wall patch behind: in-box fraction
    patch = hb.add_box((11.9, 0.5, 1.3), (0.1, 1.0, 2.6))
    house = hb.build(offset=OFFSET)
    start = sum(len(p[1]) for p in hb.parts[:patch])
    fo = house.face_object.copy()
    fo[start : start + len(hb.parts[patch][1])] = holey
    house = dataclasses.replace(house, face_object=fo)
    dec, _ = _decide(house, _pose(1.0, 3.0, 0.0))
    reasons = dict(zip(dec.objects.tolist(), dec.reasons))
    assert reasons[near] == ""
    assert reasons[far] == "distance"
    assert reasons[hidden] == "visible_pixels" and dec.visible_pixels[list(dec.objects).index(hidden)] == 0
    assert reasons[side] == "fov"
    assert reasons[high] == "height"
    j = list(dec.objects).index(holey)
    assert reasons[holey] == "in_box_fraction", (dec.visible_pixels[j], dec.in_box_fraction[j])
    assert dec.in_box_fraction[j] < 0.8 and dec.points_in_box[j] >= 35
    # Too few points: the same frame with a stricter point threshold rejects the near chair for that reason.
    strict = dataclasses.replace(SENSOR.filters, min_points_in_box=10**6)
    dec2, _ = _decide(house, _pose(1.0, 3.0, 0.0), strict)
    assert dict(zip(dec2.objects.tolist(), dec2.reasons))[near] == "points_in_box"


@pytest.mark.parametrize("distance,expect_occluded", [(2.0, 0)])
def test_occlusion_level_of_a_half_hidden_chair(distance, expect_occluded):
    hb = HouseBuilder()
    hb.room(0, 0, 8, 6)
    k = hb.chair(1.0 + distance, 3.0, size=(0.5, 0.8, 0.9))
    house = hb.build(offset=OFFSET)
    dec, _ = _decide(house, _pose(1.0, 3.0, 0.0))
    k = list(dec.objects).index(k)
    assert dec.occluded[k] == expect_occluded and dec.visible_fraction[k] == pytest.approx(1.0, abs=0.02)
    # A screen hiding the chair's left half.
    hb.add_box((2.0, 3.25, 0.6), (0.05, 0.5, 1.2))
    house = hb.build(offset=OFFSET)
    dec, _ = _decide(house, _pose(1.0, 3.0, 0.0))
    assert dec.reasons[k] == ""
    assert 0.25 < dec.visible_fraction[k] < 0.75 and dec.occluded[k] == 1


def _assert_same_decisions(coarse, full):
    """The coarse two-stage decisions equal the every-pixel ones; counts are exact or lower bounds of the full ones."""
    assert coarse.reasons == full.reasons
    assert full.exact.all()
    ex = coarse.exact
    np.testing.assert_array_equal(coarse.visible_pixels[ex], full.visible_pixels[ex])
    np.testing.assert_array_equal(coarse.points_in_box[ex], full.points_in_box[ex])
    assert (coarse.visible_pixels[~ex] <= full.visible_pixels[~ex]).all()
    assert (coarse.points_in_box[~ex] <= full.points_in_box[~ex]).all()
    # A lower bound is only ever reported for a kept box: every rejection is decided on exact counts.
    assert all(coarse.reasons[k] == "" for k in np.flatnonzero(~ex))
    return int((~ex).sum())


@pytest.mark.parametrize("realism", ["clean", "default"])
def test_coarse_visibility_gives_the_full_grid_decisions_on_synthetic_houses(tmp_path, realism):
    from mpchair.matterport.house import read_house
    from mpchair.matterport.source import find_houses
    from mpchair.synth import synthesize_house, write_house
    from mpchair.synth.realism import CLEAN, DEFAULT

    synth = synthesize_house(1, levels=1, realism=CLEAN if realism == "clean" else DEFAULT)
    write_house(tmp_path, synth)
    house = read_house(find_houses(tmp_path)[synth.id])
    rng = np.random.default_rng(0)
    lo, hi = house.vertices.min(axis=0), house.vertices.max(axis=0)
    floor = lo[2] + 0.05
    rc = make_raycaster(house.vertices, house.faces)
    lower_bounds = rays_coarse = rays_full = 0
    chairs = np.array([o.aligned_box[:3] for o in house.objects if o.mpcat40_index == 3])
    for _ in range(30):
        # Stand near a random chair, looking roughly at it, so that near (large-region) chairs are common.
        target = chairs[rng.integers(len(chairs))]
        ang = rng.uniform(0, 2 * np.pi)
        r = rng.uniform(0.8, 3.0)
        x, y = target[0] + r * np.cos(ang), target[1] + r * np.sin(ang)
        yaw = np.arctan2(target[1] - y, target[0] - x) + rng.uniform(-0.5, 0.5)
        c, s = np.cos(yaw), np.sin(yaw)
        pose = np.eye(4)
        pose[:2, :2] = [[c, -s], [s, c]]
        pose[:3, 3] = [np.clip(x, lo[0], hi[0]), np.clip(y, lo[1], hi[1]), floor + 1.0]
        coarse, _ = _decide(house, pose, rc=rc)
        full, _ = _decide(house, pose, coarse=False, rc=rc)
        lower_bounds += _assert_same_decisions(coarse, full)
        rays_coarse += coarse.dense_rays
        rays_full += full.dense_rays
    assert lower_bounds > 10  # the coarse path was really taken ...
    # ... and saved rays: about half on a clean house (occluded chairs cost full regions); on a realistic one (clutter
    # around the chairs, holes) most chairs need their full region and it saves about a tenth
    assert rays_coarse < (0.75 if realism == "clean" else 0.97) * rays_full


def test_coarse_visibility_on_constructed_cases_with_out_of_box_faces():
    hb = HouseBuilder()
    hb.room(0, 0, 12, 8)
    near = hb.chair(2.2, 3.0)
    holey = hb.chair(2.5, 1.9)  # its label leaks onto a wall patch: hits outside its box decide the fraction
    patch = hb.add_box((3.3, 0.6, 0.5), (0.1, 0.5, 0.6))
    house = hb.build(offset=OFFSET)
    start = sum(len(p[1]) for p in hb.parts[:patch])
    fo = house.face_object.copy()
    fo[start : start + len(hb.parts[patch][1])] = holey
    house = dataclasses.replace(house, face_object=fo)
    for x, yaw in ((1.0, 0.0), (0.6, -0.3), (1.2, -0.6)):
        coarse, _ = _decide(house, _pose(x, 3.0, yaw))
        full, _ = _decide(house, _pose(x, 3.0, yaw), coarse=False)
        _assert_same_decisions(coarse, full)
        assert dict(zip(coarse.objects.tolist(), coarse.reasons))[near] == ""
