"""Raycasting backends: exact hits on known geometry far from the origin, misses, and Embree == Open3D."""

from __future__ import annotations

import numpy as np
import pytest
from helpers_scenes import HouseBuilder

from mpchair.scan.raycast import EmbreeRaycaster, make_raycaster
from mpchair.scan.sensors import load_sensor, scan_directions

OFFSET = np.array([12345.0, -54321.0, 37.0])  # houses sit at a random global offset


def _room():
    hb = HouseBuilder()
    hb.room(0, 0, 8, 6)
    hb.chair(3, 2, 0.4)
    hb.chair(5, 4, -1.0, size=(0.6, 0.5, 0.8))
    return hb.build(offset=OFFSET)


def test_embree_hits_are_exact_far_from_the_origin():
    house = _room()
    rc = make_raycaster(house.vertices, house.faces, "embree")
    o = OFFSET + [1.0, 3.0, 1.0]
    d = np.array([[-1.0, 0, 0], [0, 0, -1.0], [0, 0, 2.0], [1.0, 0, 0]])
    t, face = rc.cast(o, d)
    # wall x = 0 at 1 m, floor at 1 m, ceiling 1.6 m above (t in units of the 2x-long direction: 0.8), the far
    # wall at 7 m.
    np.testing.assert_allclose(t, [1.0, 1.0, 0.8, 7.0], atol=1e-9)
    assert (face >= 0).all()
    assert house.face_category[face[1]] == 2 and house.face_category[face[0]] == 1
    t, face = rc.cast(OFFSET + [100.0, 0, 0], np.array([[1.0, 0, 0]]))
    assert t[0] == np.inf and face[0] == -1


def test_embree_and_open3d_agree_on_a_full_scan():
    pytest.importorskip("open3d", reason="open3d-cpu not installed")
    house = _room()
    a = make_raycaster(house.vertices, house.faces, "embree")
    b = make_raycaster(house.vertices, house.faces, "open3d")
    d = scan_directions(load_sensor("mp3d-depth90"))
    rng = np.random.default_rng(0)
    for _ in range(3):
        yaw = rng.uniform(0, 2 * np.pi)
        R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
        o = OFFSET + [rng.uniform(1, 7), rng.uniform(1, 5), 1.0]
        ta, fa = a.cast(o, d @ R.T)
        tb, fb = b.cast(o, d @ R.T)
        assert np.isfinite(ta).all()  # a closed room: every ray hits
        # Same hit points to 1e-4 m; the face can differ only on shared edges, where the point is the same.
        np.testing.assert_allclose(ta, tb, atol=1e-4)
        assert np.mean(fa == fb) > 0.999
        same = fa == fb
        np.testing.assert_array_equal(house.face_object[fa[same]], house.face_object[fb[same]])


def test_bad_meshes_and_backends_are_rejected():
    from mpchair.core.errors import InputError

    with pytest.raises(InputError, match="available: embree, open3d"):
        make_raycaster(np.zeros((3, 3)), np.array([[0, 1, 2]]), "optix")
    with pytest.raises(ValueError, match="out of range"):
        EmbreeRaycaster(np.zeros((3, 3)), np.array([[0, 1, 5]]))
