"""Synthetic houses: written in the release format, read back exactly, deterministic, and plausible homes.

These tests are about the procedural recipe itself (watertight chairs tight in their boxes, one ceiling hole, the five
chair styles), so they ask for ``realism=CLEAN``; the realism model has its own tests (test_synth_realism.py)."""

from __future__ import annotations

import hashlib
import math
import re
from pathlib import Path

import numpy as np
import pytest
import trimesh
from shapely.geometry import Polygon
from shapely.ops import unary_union

from mpchair.geometry import bev_polygons, points_in_boxes
from mpchair.matterport import find_houses, read_house
from mpchair.synth import plan_houses, synthesize_house, write_house, write_synthetic_houses
from mpchair.synth.realism import CLEAN

SEED = 11
N = 2


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> tuple[Path, list]:
    root = tmp_path_factory.mktemp("synth")
    ids = write_synthetic_houses(root, N, SEED, realism=CLEAN)
    plan = plan_houses(N, SEED)
    assert ids == [p[0] for p in plan]
    built = [synthesize_house(hs, hid, levels=lv, realism=CLEAN) for hid, hs, lv in plan]
    return root, built


@pytest.fixture(scope="module")
def houses(written) -> list:
    root, built = written
    found = find_houses(root)
    return [read_house(found[b.id]) for b in built]


def _digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}  # fmt: skip


def test_round_trip_objects_categories_and_boxes(written, houses) -> None:
    _, built = written
    for syn, h in zip(built, houses):
        assert h.id == syn.id and len(h.objects) == len(syn.objects)
        for o, g in zip(h.objects, syn.objects):
            assert (o.index, o.region, o.raw_category, o.mapping_index) == (g.index, g.region, g.raw_category,
                                                                          g.mapping_index)  # fmt: skip
            assert (o.mpcat40_index, o.mpcat40_name) == (g.mpcat40_index, g.mpcat40_name)
            np.testing.assert_allclose(o.aligned_box[:6], g.aligned_box[:6], atol=1e-5)
            dyaw = (o.aligned_box[6] - g.aligned_box[6] + math.pi / 2) % math.pi - math.pi / 2
            assert abs(dyaw) < 1e-5
            assert o.tilt_deg < 1e-4
        # Face labels follow the material chain; the injected annotation drift shows up as the mismatch rate.
        np.testing.assert_array_equal(h.face_object, syn.segment_id)
        mp = np.array([g.mpcat40_index for g in syn.objects] + [-1])
        np.testing.assert_array_equal(h.face_category, mp[syn.segment_id])
        assert h.label_mismatch_rate == pytest.approx(syn.mismatched_faces / len(syn.faces))
        assert syn.mismatched_faces > 0
        assert h.unlabelled_faces == syn.unlabelled_faces > 0
        np.testing.assert_allclose(h.vertices, syn.vertices, atol=1e-5)  # stored as float32
        np.testing.assert_array_equal(h.faces, syn.faces)
        assert len(h.regions) == len(syn.house_file.regions) and len(h.levels) == syn.n_levels
        assert h.warnings == ()


def test_release_format_records(written) -> None:
    root, built = written
    for syn in built:
        text = (root / "v1" / "scans" / syn.id / "house_segmentations" / f"{syn.id}.house").read_text()
        lines = text.splitlines()
        assert lines[0] == "ASCII 1.1" and lines[1].startswith("H  ")
        letters = [ln[0] for ln in lines[1:]]
        # Release order: H L R P(portals) S V P(panoramas) I C O E, every kind present.
        order = re.sub(r"(.)\1*", r"\1", "".join(letters))
        assert order == "HLRPSVPICOE"
        assert all(len(ln.split()) == {"H": 29, "L": 18, "R": 20, "S": 22, "V": 13, "I": 41, "C": 11, "O": 24,
                                       "E": 19}.get(ln[0], len(ln.split())) for ln in lines[1:])  # fmt: skip
        c_names = [ln.split()[3] for ln in lines if ln.startswith("C ")]
        assert "dining#chair" in c_names and "sofa#chair" in c_names and "wall#\\other#room" in c_names
        semseg = (root / "v1" / "scans" / syn.id / "house_segmentations" / f"{syn.id}.semseg.json").read_bytes()
        assert b'"wall \\other room"' in semseg  # the invalid escape real files have
        ply = (root / "v1" / "scans" / syn.id / "house_segmentations" / f"{syn.id}.ply").read_bytes()
        assert ply.startswith(b"ply\nformat binary_little_endian 1.0\nelement vertex ")


def test_same_seed_same_bytes_and_zip_layout(tmp_path: Path, written) -> None:
    root, _ = written
    write_synthetic_houses(tmp_path / "again", N, SEED, realism=CLEAN)
    assert _digest(tmp_path / "again") == _digest(root)
    write_synthetic_houses(tmp_path / "z1", 1, SEED, zip_files=True)
    write_synthetic_houses(tmp_path / "z2", 1, SEED, zip_files=True)
    assert _digest(tmp_path / "z1") == _digest(tmp_path / "z2")
    (hid,) = find_houses(tmp_path / "z1")
    assert list(_digest(tmp_path / "z1")) == [f"v1/scans/{hid}/house_segmentations.zip"]
    write_synthetic_houses(tmp_path / "other", 1, SEED + 1)
    assert list(find_houses(tmp_path / "other")) != [hid]


def test_houses_are_plausible_homes(written, houses) -> None:
    _, built = written
    styles, classes = set(), set()
    for syn, h in zip(built, houses):
        chairs = [o for o in syn.objects if o.mpcat40_index == 3]
        assert 10 <= len(chairs) <= 30
        styles |= {o.style for o in chairs}
        classes |= {o.mpcat40_name for o in syn.objects}
        assert len(h.faces) <= 200_000
        assert len(h.portals) >= len(h.regions) - syn.n_levels and len(h.panoramas) == len(h.regions)
        # Nothing axis-aligned to the world: walls are rotated by the global yaw.
        walls = np.array([o.aligned_box[6] for o in syn.objects if o.style == "wall"])
        assert np.all(np.abs(((walls + math.pi / 4) % (math.pi / 2)) - math.pi / 4) > 1e-3)
        for r in h.regions:
            poly = Polygon(r.floor_polygon)
            edges = np.linalg.norm(np.diff(np.vstack([r.floor_polygon, r.floor_polygon[:1]]), axis=0), axis=1)
            assert edges.min() >= 3.0 - 1e-6  # rooms at least ~3 x 3 m
            if r.label == "s":
                continue
            furniture = [o for o in syn.objects if o.region == r.index and o.style not in
                         ("wall", "floor", "ceiling", "window", "railing", "rail", "stairs")]  # fmt: skip
            if furniture:
                foot = unary_union([Polygon(p) for p in bev_polygons(np.stack([o.aligned_box for o in furniture]))])
                assert foot.intersection(poly).area <= 0.6 * poly.area  # free floor for viewpoints
    assert styles == {"dining", "armchair", "office", "folding", "lounge"}
    assert {"stool", "sofa", "table", "cabinet", "bed", "seating", "misc"} <= classes
    assert built[0].n_levels == 2 and any(o.style == "stairs" for o in built[0].objects)
    sizes = np.stack([o.aligned_box[3:6] for s in built for o in s.objects if o.mpcat40_index == 3])
    mean = sizes.mean(axis=0)
    assert 0.65 < mean[0] < 1.1 and 0.5 < mean[1] < 0.8 and 0.8 < mean[2] < 1.05


#: Mean aligned chair box of the original dataset, l x w x h in metres (docs/original-generator.md, stat_boxes.py).
MP3D_CHAIR_MEAN_LWH = (0.960, 0.667, 0.884)


def test_chair_sizes_match_matterport_mean() -> None:
    # Many houses (about 0.05 s each): one house has ~16 chairs, far too few for a stable mean. The construction
    # boxes equal what the reader derives from the O records (round-trip test above), so no files are written.
    sizes: dict[str, list[np.ndarray]] = {}
    for hid, hs, lv in plan_houses(40, SEED):
        for o in synthesize_house(hs, hid, levels=lv, realism=CLEAN).objects:
            if o.mpcat40_index == 3:
                sizes.setdefault(o.style, []).append(o.aligned_box[3:6])
    allsizes = np.concatenate([np.stack(v) for v in sizes.values()])
    assert len(allsizes) >= 400
    np.testing.assert_allclose(allsizes.mean(axis=0), MP3D_CHAIR_MEAN_LWH, atol=0.06)
    # The mean must come from a mix of realistic styles, not from every chair being an average box.
    mean = {k: np.stack(v).mean(axis=0) for k, v in sizes.items()}
    assert set(mean) == {"dining", "armchair", "office", "folding", "lounge"}
    assert all(len(v) >= 0.05 * len(allsizes) for v in sizes.values())
    assert mean["dining"][0] < 0.6 and mean["folding"][0] < 0.5 and mean["lounge"][0] > 1.5
    assert mean["armchair"][1] > 0.8 and mean["office"][2] > 0.95 and mean["lounge"][2] < 0.9


def test_chairs_are_closed_surfaces_tight_in_their_boxes(houses) -> None:
    for h in houses:
        for o in (o for o in h.objects if o.mpcat40_index == 3):
            k = h.objects.index(o)
            faces = h.faces[h.face_object == k]
            mesh = trimesh.Trimesh(h.vertices, faces, process=False)
            assert mesh.is_watertight  # legs, seat, back are closed parts
            used = h.vertices[np.unique(faces)]
            grown = o.aligned_box.copy()
            grown[3:6] += 2e-4  # float32 vertices sit on the box faces
            assert points_in_boxes(used, grown[None]).all()
            shrunk = o.aligned_box.copy()
            shrunk[3:6] -= 2e-3
            assert not points_in_boxes(used, shrunk[None]).all()  # tight: the box is the parts' extent


def test_mesh_has_a_hole_rays_escape_through(houses) -> None:
    h = houses[0]
    mesh = trimesh.Trimesh(h.vertices, h.faces, process=False)
    top = max(r.level for r in h.regions)
    origins = []
    for r in h.regions:
        if r.level == top:
            lo, hi = r.floor_polygon.min(axis=0), r.floor_polygon.max(axis=0)
            gx, gy = np.meshgrid(np.linspace(lo[0] + 0.3, hi[0] - 0.3, 25), np.linspace(lo[1] + 0.3, hi[1] - 0.3, 25))
            origins.append(np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, r.floor_z + 2.3)]))
    o = np.vstack(origins)
    hit = mesh.ray.intersects_any(o, np.tile([0.0, 0.0, 1.0], (len(o), 1)))
    assert 0 < np.count_nonzero(~hit) < 0.2 * len(o)  # an unreconstructed patch of ceiling, not a missing roof


def test_subdivided_house_has_the_same_surfaces_objects_and_labels(tmp_path):
    from mpchair.synth import subdivide_house

    base = synthesize_house(5, levels=1, realism=CLEAN)
    fine = subdivide_house(base, 2)
    assert len(fine.faces) == 16 * len(base.faces)
    # Children of face f are faces 16 f .. 16 f + 15: same labels, and together exactly f's area, inside f's plane.
    np.testing.assert_array_equal(fine.material_id, np.repeat(base.material_id, 16))
    np.testing.assert_array_equal(fine.category_id, np.repeat(base.category_id, 16))

    def areas(v, f):
        return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)

    np.testing.assert_allclose(areas(fine.vertices, fine.faces).reshape(-1, 16).sum(axis=1),
                               areas(base.vertices, base.faces), rtol=1e-9, atol=1e-12)
    a, b, c = (base.vertices[base.faces[:, k]] for k in range(3))
    normal = np.cross(b - a, c - a)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    child = fine.vertices[fine.faces].reshape(len(base.faces), 16 * 3, 3)
    dist = np.einsum("fkj,fj->fk", child - a[:, None], normal)
    assert np.abs(dist).max() < 1e-9
    # Written and read back, the objects and their aligned boxes are those of the coarse house.
    write_house(tmp_path, fine)
    house = read_house(find_houses(tmp_path)[fine.id])
    assert len(house.faces) == len(fine.faces)
    for o, truth in zip(house.objects, base.objects):
        np.testing.assert_allclose(o.aligned_box, truth.aligned_box, atol=1e-5)
