"""Robot motion for streams: free space on a hand-made house, routes (rules, collision-free shortcut paths) and the
unicycle drive (limits, look-around, goal, exact frame sampling)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers_scenes import WALL, HouseBuilder

from mpchair.dataset.frame import build_context, floor_areas
from mpchair.scan.viewpoints import ViewpointParams
from mpchair.stream.episodes import EpisodeSettings, plan_episode
from mpchair.stream.freespace import free_space
from mpchair.stream.routes import RouteRules, grid_path, sample_route, segment_free, shortcut
from mpchair.stream.unicycle import STEP_US, Limits, drive, frame_times, sample_poses


@pytest.fixture(scope="module")
def house():
    """A 6 x 4 m room split by a wall from y = 0 to y = 2.8 at x = 3 (a 1.2 m gap at the top), one chair."""
    hb = HouseBuilder()
    hb.room(0.0, 0.0, 6.0, 4.0)
    hb.add_box((3.0, 1.4, 1.3), (0.1, 2.8, 2.6), category=WALL)
    hb.chair(1.0, 3.3)
    h = hb.build()
    ctx = build_context(h, frozenset({3}))
    spaces = free_space(floor_areas(h), ctx.raycaster, ctx.floor_ok, ctx.normal_z, ViewpointParams(robot_radius=0.25))
    return h, spaces


def test_free_space_keeps_the_robot_radius_from_walls(house):
    _, spaces = house
    assert len(spaces) == 1
    s = spaces[0]
    xy = s.centres_of(np.argwhere(s.free))
    # every free cell keeps 0.25 m from the outer walls (inner faces at 0, 6 / 0, 4) and from the middle wall
    assert xy[:, 0].min() >= 0.25 - 1e-9 and xy[:, 0].max() <= 6 - 0.25 + 1e-9
    assert xy[:, 1].min() >= 0.25 - 1e-9 and xy[:, 1].max() <= 4 - 0.25 + 1e-9
    near_wall = (np.abs(xy[:, 0] - 3.0) < 0.05 + 0.25 - 1e-6) & (xy[:, 1] < 2.8)
    assert not near_wall.any()
    # the two halves are one island, joined through the gap above the wall
    assert len(np.unique(s.islands[s.free])) == 1
    assert s.is_free(np.array([[1.0, 1.0], [5.0, 1.0], [3.0, 3.4]])).all()
    assert not s.is_free(np.array([[3.0, 1.0], [1.0, 3.3], [-1.0, 1.0]])).any()  # wall, chair, off the grid


def test_routes_follow_the_rules_and_stay_in_free_space(house):
    _, spaces = house
    rules = RouteRules(min_geodesic=4.0, max_geodesic=8.0, min_ratio=1.5, min_island_radius=1.0)
    for seed in range(4):
        r = sample_route(np.random.default_rng(seed), spaces, rules)
        assert 4.0 <= r.geodesic <= 8.0 and r.geodesic / r.euclidean >= 1.5
        # start and goal on either side of the wall: the path goes round it, every segment through free cells
        assert (r.waypoints[0, 0] - 3) * (r.waypoints[-1, 0] - 3) < 0
        assert len(r.waypoints) >= 3
        assert all(segment_free(spaces[0], a, b) for a, b in zip(r.waypoints[:-1], r.waypoints[1:]))
        # shortcutting the clearance-weighted grid path never lengthens it
        w = spaces[0].free.shape[1]
        (r0, c0), (r1, c1) = spaces[0].cells_of(r.waypoints[[0, -1]])
        grid = grid_path(spaces[0], int(r0 * w + c0), int(r1 * w + c1), rules)
        assert np.array_equal(shortcut(spaces[0], grid), r.waypoints)
        assert r.length <= np.linalg.norm(np.diff(grid, axis=0), axis=1).sum() + 1e-9 and len(grid) > len(r.waypoints)
    a = sample_route(np.random.default_rng(7), spaces, rules)
    b = sample_route(np.random.default_rng(7), spaces, rules)
    assert np.array_equal(a.waypoints, b.waypoints)
    with pytest.raises(ValueError, match="no start/goal pair"):
        sample_route(np.random.default_rng(0), spaces, RouteRules(min_geodesic=50, max_geodesic=60), tries=3)


def test_drive_respects_the_limits_and_reaches_the_goal():
    lim = Limits(speed=0.5, turn_rate=1.0, accel=0.5, turn_accel=2.0)
    wp = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 2.0], [4.5, 3.0]])
    tr = drive(wp, start_yaw=2.0, limits=lim, look_around=True)
    dt = STEP_US * 1e-6
    assert np.abs(tr.v).max() <= lim.speed + 1e-12 and np.abs(tr.omega).max() <= lim.turn_rate + 1e-12
    assert np.abs(np.diff(tr.v)).max() <= lim.accel * dt + 1e-12
    assert np.abs(np.diff(tr.omega)).max() <= lim.turn_accel * dt + 1e-12
    assert tr.v.max() == pytest.approx(lim.speed)  # it does reach top speed on the 3 m legs
    assert np.linalg.norm(tr.xy[-1] - wp[-1]) < lim.goal_tolerance + 0.02
    assert tr.v[-1] == 0.0 and tr.omega[-1] == 0.0
    # the look-around: a full turn in place first (position unchanged while the yaw grows by 2 pi)
    turned = np.flatnonzero(tr.yaw - 2.0 >= 2 * math.pi - 1e-3)[0]
    assert np.array_equal(tr.xy[: turned + 1], np.zeros((turned + 1, 2)))
    # heading follows the path: the robot never strays far from the polyline
    seg = np.diff(wp, axis=0)
    rel = [tr.xy - wp[j] for j in range(len(seg))]
    d = np.min([np.abs(seg[j, 0] * rel[j][:, 1] - seg[j, 1] * rel[j][:, 0]) / np.linalg.norm(seg[j])
                for j in range(len(seg))], axis=0)
    assert d.max() < 0.15


def test_frames_sample_the_drive_at_exact_microseconds():
    tr = drive(np.array([[0.0, 0.0], [2.0, 1.0]]), 0.3, Limits(), look_around=False)
    t10, t20 = frame_times(10, tr.end_us), frame_times(20, tr.end_us)
    assert t10.dtype == np.int64 and np.array_equal(t10, np.arange(len(t10)) * 100_000)
    assert np.array_equal(frame_times(3, 1_000_000), [0, 333_333, 666_667, 1_000_000])
    xy10, yaw10 = sample_poses(tr, t10)
    xy20, yaw20 = sample_poses(tr, t20)
    # a 10 Hz stream is exactly every second frame of the 20 Hz stream
    assert np.array_equal(xy10, xy20[::2][: len(xy10)]) and np.array_equal(yaw10, yaw20[::2][: len(yaw10)])
    # between two states: linear
    xy, _ = sample_poses(tr, np.array([STEP_US * 50 + STEP_US // 2]))
    assert np.allclose(xy[0], (tr.xy[50] + tr.xy[51]) / 2)


def test_a_still_robot_holds_its_pose(house):
    _, spaces = house
    es = EpisodeSettings(rate=5.0, limits=Limits(speed=0.0, turn_rate=0.0), rules=RouteRules(min_island_radius=1.0),
                         height=1.0, look_around=True, duration_us=2_000_000, seed=3)
    ep = plan_episode(spaces, "TESTHOUSE01", 0, es)
    assert np.array_equal(ep.times_us, np.arange(11) * 200_000)
    assert (ep.poses == ep.poses[0]).all()
    assert ep.poses[0][2, 3] == pytest.approx(1.0, abs=0.02)  # the sensor height above the floor at z = 0
    with pytest.raises(ValueError, match="needs a duration"):
        plan_episode(spaces, "TESTHOUSE01", 0, EpisodeSettings(5.0, Limits(speed=0.0), RouteRules(), 1.0, True,
                                                               None, 3))


def test_free_space_from_a_habitat_navmesh(tmp_path):
    import shapely

    from mpchair.matterport.house import read_house
    from mpchair.matterport.source import find_houses
    from mpchair.scan.navmesh import island_labels
    from mpchair.stream.freespace import navmesh_areas
    from mpchair.synth import synthesize_house, write_house

    synth = synthesize_house(7, levels=1)
    write_house(tmp_path, synth, layout="habitat")
    h = read_house(find_houses(tmp_path)[synth.id])
    areas = navmesh_areas(h.navmesh)
    assert len(areas) == int((island_labels(h.navmesh)[h.navmesh.triangle_poly] >= 0).sum())
    ctx = build_context(h, frozenset({3}))
    spaces = free_space(areas, ctx.raycaster, ctx.floor_ok, ctx.normal_z, ViewpointParams())
    big = max(spaces, key=lambda s: s.free.sum())
    assert big.free.sum() > 5000  # 5 cm cells: more than 12.5 m^2 to drive in
    # every free cell lies on the walkable surface of its island, and is a valid viewpoint (validated like generate's)
    walk = shapely.union_all([shapely.Polygon(a.polygon) for a in areas if a.level == big.level])
    xy = big.centres_of(np.argwhere(big.free))
    assert shapely.contains_xy(walk.buffer(1e-6), xy[:, 0], xy[:, 1]).all()
    r = sample_route(np.random.default_rng(0), spaces, RouteRules(min_geodesic=3.0))
    assert all(segment_free(big, a, b) for a, b in zip(r.waypoints[:-1], r.waypoints[1:])) and r.level == big.level
