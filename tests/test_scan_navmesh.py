"""habitat ``.navmesh`` files read with numpy (MSET v1/v2 written in the real byte layout), islands and habitat's island
radius, area-weighted sampling, snapping, bad files, and ``--viewpoints navmesh`` on a synthetic house."""

from __future__ import annotations

import shutil
import struct
from pathlib import Path

import numpy as np
import pytest

from mpchair.cli import main
from mpchair.core.errors import InputError
from mpchair.dataset.frame import build_context, frame_rng
from mpchair.geometry import mp3d_to_habitat
from mpchair.matterport import read_house
from mpchair.matterport.navmesh import POLY_DISABLED, encode_navmesh, read_navmesh
from mpchair.scan.navmesh import NavmeshSampler, island_labels, island_radii, snap_points
from mpchair.scan.viewpoints import ViewpointParams, viewpoint_stream
from mpchair.synth import synthesize_house, write_house
from mpchair.synth.realism import CLEAN

# Two unit quads sharing an edge (one island, the second 0.1 m higher at its far side), a triangle far away (a second
# island) and a zero-area triangle (unusable). World frame, z up.
V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0.1], [2, 1, 0.1], [5, 5, 0], [6, 5, 0], [6, 6, 0],
              [8, 8, 0], [9, 8, 0], [10, 8, 0]], dtype=float)  # fmt: skip
P = np.array([[0, 1, 2, 3], [1, 4, 5, 2], [6, 7, 8, -1], [9, 10, 11, -1]])


def _corners(polys: list[list[int]]) -> np.ndarray:
    return np.concatenate([V[p] for p in polys])


@pytest.mark.parametrize("version", [1, 2])
def test_mset_file_layout_and_round_trip(version: int) -> None:
    data = encode_navmesh(V, P, version=version)
    magic, ver, tiles = struct.unpack_from("<iii", data)
    assert (magic, ver, tiles) == (0x4D534554, version, 1) and data[:4] == b"TESM"
    at = 40 + (56 if version == 2 else 0)
    ref, size = struct.unpack_from("<Ii", data, at)
    assert at + 8 + size == len(data) and data[at + 8 : at + 12] == b"VAND"  # 'DNAV' little-endian
    # dtMeshHeader counts: 4 polys, 12 verts, 3 links (internal edge sides: the shared edge twice... and no others)
    counts = struct.unpack_from("<15i", data, at + 8)
    assert counts[1] == 7 and counts[6:9] == (4, 12, 2) and counts[9] == 4 and counts[11] == 6 and counts[12] == 4
    # Vertices are stored in habitat's y-up frame.
    stored = np.frombuffer(data, "<f4", 36, at + 8 + 100).reshape(-1, 3)
    np.testing.assert_allclose(stored, mp3d_to_habitat(V), atol=1e-6)
    nav = read_navmesh(data, "x.navmesh")
    assert nav.version == version and (nav.settings is None) == (version == 1)
    if version == 2:
        assert nav.settings["agent_radius"] == pytest.approx(0.1) and nav.settings["cell_height"] == pytest.approx(0.2)
    assert nav.walkable_height == pytest.approx(1.5) and nav.walkable_climb == pytest.approx(0.2)
    np.testing.assert_allclose(nav.vertices, V, atol=1e-6)
    assert nav.links.tolist() == [[0, 1]]
    assert nav.triangle_poly.tolist() == [0, 0, 1, 1, 2, 3]
    np.testing.assert_allclose(nav.triangles[2], V[[1, 4, 5]], atol=1e-6)


def test_islands_radius_sampling_and_snapping() -> None:
    nav = read_navmesh(encode_navmesh(V, P))
    labels = island_labels(nav)
    assert labels.tolist() == [0, 0, 1, -1]  # the zero-area polygon is unusable
    c = _corners([[0, 1, 2, 3], [1, 4, 5, 2]])  # habitat: every corner of every polygon, duplicates counted
    expect0 = np.linalg.norm(c - c.mean(axis=0), axis=1).max()
    c1 = V[[6, 7, 8]]
    np.testing.assert_allclose(island_radii(nav, labels), [expect0, np.linalg.norm(c1 - c1.mean(0), axis=1).max()])
    assert expect0 == pytest.approx(1.1205, abs=1e-4)

    s = NavmeshSampler(nav, min_island_radius=0.5)
    assert s.islands.tolist() == [0, 1]
    np.testing.assert_allclose(s.island_area, [2.0, 0.5], atol=1e-6)
    rng = np.random.default_rng(0)
    pts = np.array([s.sample(rng) for _ in range(4000)])
    share = np.mean(pts[:, 0] == 1)
    assert share == pytest.approx(0.5 / 2.5, abs=0.03)  # area-weighted: 20 % on the small island
    on0 = pts[pts[:, 0] == 0]
    assert np.mean(on0[:, 1] > 1) == pytest.approx(0.5, abs=0.04)  # uniform over both quads
    # Points lie on the surface: z of the sloped quad is 0.1 * (x - 1).
    sloped = on0[on0[:, 1] > 1]
    np.testing.assert_allclose(sloped[:, 3], 0.1 * (sloped[:, 1] - 1), atol=1e-6)
    with pytest.raises(ValueError, match=r"no navmesh island has a radius of at least 1.5 m \(largest: 1.12 m\)"):
        NavmeshSampler(nav)

    snapped, tri = snap_points(nav, [[0.5, 0.5, 3.0], [-1.0, -1.0, 0.0], [1.5, 2.0, 0.0], [9.0, 8.0, 0.0]])
    np.testing.assert_allclose(snapped[0], [0.5, 0.5, 0.0], atol=1e-6)
    np.testing.assert_allclose(snapped[1], [0.0, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(snapped[2][1], 1.0, atol=1e-6)  # onto the quads' far edge
    assert nav.triangle_poly[tri[3]] != 3  # never onto the unusable polygon

    flags = np.array([1, 1 | POLY_DISABLED, 1, 1])
    assert island_labels(read_navmesh(encode_navmesh(V, P, flags=flags))).tolist() == [0, -1, 1, -1]


def test_bad_navmesh_files_give_one_clean_error() -> None:
    good = encode_navmesh(V, P)
    dnav = 40 + 8
    cases = [
        (b"XXXX" + good[4:], "not a habitat navmesh"),
        (good[:4] + struct.pack("<i", 3) + good[8:], "unsupported navmesh version 3"),
        (good[:-3], "navmesh is truncated: tile 0 declares"),
        (good[:30], "navmesh is truncated: header needs 40 bytes"),
        (good[:dnav] + b"XXXX" + good[dnav + 4 :], "bad Detour magic"),
        (good[:dnav + 4] + struct.pack("<i", 8) + good[dnav + 8 :], "Detour data version 8, expected 7"),
        (good + b"\0", "1 bytes after its last tile"),
        (good[:dnav + 24] + struct.pack("<i", 5) + good[dnav + 28 :], "beyond its tile's declared end"),
        (good[:dnav + 24] + struct.pack("<i", 3) + good[dnav + 28 :], "4 detail meshes for 3 polygons"),
        (good[:dnav + 48] + struct.pack("<i", 3) + good[dnav + 52 :],
         "declares 532 bytes but its header.s arrays take 516"),
    ]  # fmt: skip
    for data, message in cases:
        with pytest.raises(InputError, match=message) as e:
            read_navmesh(data, "bad.navmesh")
        assert e.value.path == "bad.navmesh" and "\n" not in str(e.value)


@pytest.fixture(scope="module")
def habitat_house(tmp_path_factory):
    root = tmp_path_factory.mktemp("nav")
    syn = synthesize_house(7, levels=1, realism=CLEAN)  # flat floors: the navmesh lies on the mesh floor exactly
    write_house(root, syn, layout="habitat")
    return root / "mp3d" / syn.id, syn


def test_synthetic_navmesh_is_the_free_floor(habitat_house) -> None:
    folder, syn = habitat_house
    house = read_house(folder)
    nav = house.navmesh
    s = NavmeshSampler(nav)
    assert len(s.islands) >= 1 and s.island_area[s.islands].sum() > 10
    # Every navmesh point stands on a floor face of the house mesh, with nothing within the agent radius below 1.5 m.
    ctx = build_context(house, frozenset({3}), viewpoints="navmesh")
    rng = np.random.default_rng(1)
    pts = np.array([s.sample(rng)[1:] for _ in range(300)])
    t, face = ctx.raycaster.cast(pts + [0, 0, 0.5], np.tile([0.0, 0, -1], (len(pts), 1)))
    assert (face >= 0).all() and np.abs(t - 0.5).max() < 1e-5  # float32 storage
    assert set(house.face_category[face].tolist()) == {2}  # mpcat40 floor
    ang = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    dirs = np.column_stack([np.cos(ang), np.sin(ang), np.zeros(8)])
    o = np.repeat(pts + [0, 0, 0.3], 8, axis=0)
    t2, _ = ctx.raycaster.cast(o, np.tile(dirs, (len(pts), 1)))
    assert t2.min() >= 0.1 - 1e-6  # eroded by habitat's agent radius


def test_navmesh_viewpoints_are_on_large_islands_and_valid(habitat_house) -> None:
    folder, _ = habitat_house
    house = read_house(folder)
    ctx = build_context(house, frozenset({3}), viewpoints="auto")
    assert isinstance(ctx.sampler, NavmeshSampler)
    params = ViewpointParams()
    vps = list(viewpoint_stream(frame_rng(2, house.id, 0), ctx.sampler, ctx.raycaster, ctx.floor_ok, ctx.normal_z,
                                params, 120))  # fmt: skip
    assert len(vps) > 30
    again = list(viewpoint_stream(frame_rng(2, house.id, 0), ctx.sampler, ctx.raycaster, ctx.floor_ok,
                                  ctx.normal_z, params, 120))  # fmt: skip
    assert [(v.attempt, v.yaw) for v in vps] == [(v.attempt, v.yaw) for v in again]
    pos = np.array([v.position for v in vps])
    snapped, tri = snap_points(house.navmesh, pos - [0, 0, params.height])
    np.testing.assert_allclose(snapped[:, :2], pos[:, :2], atol=1e-6)  # on the navmesh, sensor 1 m above the floor
    np.testing.assert_allclose(np.array([v.floor_z for v in vps]), snapped[:, 2], atol=1e-6)
    isl = island_labels(house.navmesh)[house.navmesh.triangle_poly[tri]]
    assert (ctx.sampler.island_radius[isl] >= 1.5).all() and {v.area for v in vps} <= set(ctx.sampler.islands)
    # Our own checks still apply: clearance of the robot radius (0.25 m), more than the navmesh's 0.1 m.
    ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    dirs = np.column_stack([np.cos(ang), np.sin(ang), np.zeros(16)])
    t, _ = ctx.raycaster.cast(np.repeat(pos, 16, axis=0), np.tile(dirs, (len(pos), 1)))
    assert t.min() >= 0.25 - 1e-9
    regions = build_context(house, frozenset({3}), viewpoints="regions")
    assert not isinstance(regions.sampler, NavmeshSampler)


def test_navmesh_requested_without_one_is_a_clear_error(habitat_house, tmp_path: Path, capsys) -> None:
    folder, syn = habitat_house
    bare = tmp_path / syn.id
    shutil.copytree(folder, bare)
    (bare / f"{syn.id}.navmesh").unlink()
    with pytest.raises(SystemExit) as e:
        main(["generate", "--root", str(bare), "--house", syn.id, "--frames", "1", "--out", str(tmp_path / "o"),
              "--viewpoints", "navmesh"])  # fmt: skip
    err = capsys.readouterr().err
    assert e.value.code == 2
    assert err == f"error: house {syn.id} has no <id>.navmesh (habitat layout); use --viewpoints regions\n"
    assert not (tmp_path / "o").exists()
    (bare / f"{syn.id}.navmesh").write_bytes(b"MSET" * 20)  # the magic written big-endian
    with pytest.raises(SystemExit) as e:
        main(["houses", "--root", str(bare)])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.startswith(f"error: {bare / syn.id}.navmesh: not a habitat navmesh")
