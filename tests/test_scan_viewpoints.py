"""Viewpoints: on free floor, with clearance, not under furniture, deterministic, and a clear error when none fit."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
from helpers_scenes import TABLE, HouseBuilder

from mpchair.core.errors import InputError
from mpchair.dataset.frame import FrameSettings, build_context, frame_rng, make_frame
from mpchair.scan.sensors import load_sensor, scan_directions
from mpchair.scan.viewpoints import ViewpointParams, viewpoint_stream

OFFSET = np.array([500.0, 800.0, 12.0])


def _house():
    hb = HouseBuilder()
    hb.room(0, 0, 6, 4)
    hb.chair(2, 2, 0.5)
    hb.add_box((4.5, 2, 0.74), (1.2, 0.8, 0.04), category=TABLE)  # a table top at 0.72-0.76 m on no legs
    return hb.build(offset=OFFSET)


def _stream(ctx, params, seed, n=40):
    rng = frame_rng(seed, ctx.house.id, 0)
    return list(viewpoint_stream(rng, ctx.sampler, ctx.raycaster, ctx.floor_ok, ctx.normal_z, params, n))


def test_viewpoints_stand_on_free_floor_with_clearance():
    house = _house()
    ctx = build_context(house, frozenset({3}))
    params = ViewpointParams(height=1.25, robot_radius=0.25)
    vps = _stream(ctx, params, seed=3, n=200)
    assert len(vps) > 50
    chair = shapely.Polygon(np.array([[1.75, 1.775], [2.25, 1.775], [2.25, 2.225], [1.75, 2.225]]))
    chair = shapely.affinity.rotate(chair, 0.5, origin=(2, 2), use_radians=True)
    table = shapely.box(3.9, 1.6, 5.1, 2.4)
    for vp in vps:
        x, y, z = vp.position - OFFSET
        assert z == pytest.approx(1.25, abs=1e-9)  # floor top is z = 0
        assert 0 <= vp.yaw < 2 * np.pi
        assert min(x, y, 6 - x, 4 - y) >= 0.25 - 1e-9  # walls
        p = shapely.Point(x, y)
        assert chair.distance(p) >= 0.25 * np.cos(np.pi / 16) - 1e-6  # 16 clearance rays
        assert not table.contains(p)  # no robot under the table top
        np.testing.assert_allclose(vp.pose()[:3, 3], vp.position)


def test_viewpoint_stream_is_a_pure_function_of_the_seed():
    ctx = build_context(_house(), frozenset({3}))
    a = _stream(ctx, ViewpointParams(batch=8), seed=5)
    b = _stream(ctx, ViewpointParams(batch=3), seed=5)
    c = _stream(ctx, ViewpointParams(batch=8), seed=6)
    assert [(v.attempt, v.yaw) for v in a] == [(v.attempt, v.yaw) for v in b]
    np.testing.assert_array_equal(np.array([v.position for v in a]), np.array([v.position for v in b]))
    assert [v.yaw for v in a] != [v.yaw for v in c]


def test_no_room_for_the_robot_is_a_clear_error():
    ctx = build_context(_house(), frozenset({3}))
    sensor = load_sensor("mp3d-depth90")
    settings = FrameSettings(sensor=sensor, viewpoints=ViewpointParams(robot_radius=2.5), seed=0, max_attempts=30)
    with pytest.raises(InputError, match="found 0 valid viewpoints in 30 attempts"):
        make_frame(ctx, settings, 0, scan_directions(sensor))


def test_the_viewpoint_error_names_the_cause():
    sensor = load_sensor("mp3d-depth90")
    directions = scan_directions(sensor)

    def error(ctx, index=0, **kw) -> str:
        settings = FrameSettings(sensor=sensor, viewpoints=ViewpointParams(**kw.pop("params", {})), seed=0, **kw)
        with pytest.raises(InputError) as e:
            make_frame(ctx, settings, index, directions)
        return str(e.value)

    ctx = build_context(_house(), frozenset({3}))
    assert "clearance: of " in error(ctx, params=dict(robot_radius=2.5), max_attempts=30)
    assert "lower --robot-radius" in error(ctx, params=dict(robot_radius=2.5), max_attempts=30)
    assert "headroom: of " in error(ctx, params=dict(height=3.0), max_attempts=30)  # the ceiling is at 2.6 m
    # One attempt per frame: the frames whose single candidate is invalid fail for the attempt limit.
    failing = []
    for index in range(12):
        try:
            make_frame(ctx, FrameSettings(sensor=sensor, viewpoints=ViewpointParams(), seed=0, max_attempts=1,
                                          keep_empty=True), index, directions)
        except InputError as e:
            failing.append(str(e))
    assert failing and all("the attempt limit" in m and "raise --max-attempts (now 1)" in m for m in failing)
    # Region floors 1.5 m above the mesh's floor: no drop ray lands within 0.2 m of them.
    hb = HouseBuilder()
    hb.room(0, 0, 6, 4)
    hb.chair(2, 2, 0.5)
    hb.regions[0] = (hb.regions[0][0], 1.5, hb.regions[0][2])
    assert "the floor: none of 400 candidates" in error(build_context(hb.build(), frozenset({3})), max_attempts=30)
