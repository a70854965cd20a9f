"""The realism model of synthetic houses (mpchair.synth.realism): each knob does what it says, labels stay exact, the
clean preset is today's houses byte for byte, and the readers read every file a realistic house is written as."""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

import numpy as np
import pytest
from helpers_scenes import CHAIR, TABLE, HouseBuilder

from mpchair.labels import ObjectScenes, decide_boxes
from mpchair.labels.visibility import covering_boxes, outside_vertices
from mpchair.matterport import find_houses, read_house
from mpchair.scan.raycast import make_raycaster
from mpchair.scan.sensors import camera_calib, load_sensor
from mpchair.synth import plan_houses, synthesize_house, write_synthetic_houses
from mpchair.synth.realism import CLEAN, DEFAULT, Realism, bleed_rects, floor_tiles, realism_preset

SENSOR = load_sensor("mp3d-depth90")
#: sha256 over (relative path, bytes) of ``write_synthetic_houses(ROOT/r, 1, 4)`` and ``(ROOT/h, 1, 4,
#: layout="habitat")`` as the synthesizer wrote them before the realism model existed (commit 605047f).
TODAYS_CLEAN_BYTES = "af6b142a51d459956f81e9ae192849e409f6719208b9b495c330c6e29c6e1d5f"


def _tree_digest(root: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def _pose(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = [x, y, z]
    return T


def _decide(house, pose, rc=None):
    """The chair decisions of one frame as ``mpchair generate`` makes them (coarse first stage)."""
    objs = np.array([i for i, o in enumerate(house.objects) if o.mpcat40_index == 3])
    boxes = np.stack([house.objects[i].aligned_box for i in objs])
    rc = rc or make_raycaster(house.vertices, house.faces)
    f = SENSOR.filters
    dec = decide_boxes(boxes, objs, pose, rc, house.face_object, SENSOR.camera, camera_calib(SENSOR.camera), f,
                       ObjectScenes(house.vertices, house.faces, house.face_object),
                       covering_boxes(house.vertices, house.faces, house.face_object, objs, boxes),
                       outside_vertices(house.vertices, house.faces, house.face_object, objs, boxes, f.box_margin))
    return {int(o): (r, int(v), int(n), float(q)) for o, r, v, n, q in
            zip(dec.objects, dec.reasons, dec.visible_pixels, dec.points_in_box, dec.in_box_fraction)}, rc


def _read(tmp_path: Path, name: str, seed: int, realism: Realism):
    root = tmp_path / name
    (hid,) = write_synthetic_houses(root, 1, seed, realism=realism)
    return read_house(find_houses(root)[hid])


def test_presets_and_knob_checks() -> None:
    assert realism_preset("clean") is CLEAN and realism_preset("default") is DEFAULT
    assert CLEAN.is_clean and not DEFAULT.is_clean and not CLEAN.remesh and DEFAULT.remesh
    with pytest.raises(ValueError, match="unknown realism preset"):
        realism_preset("dirty")
    with pytest.raises(ValueError, match="probability"):
        Realism(chair_holes=1.5)
    with pytest.raises(ValueError, match=">= 0"):
        Realism(vertex_noise=-0.01)
    with pytest.raises(ValueError, match="room_size_spread"):
        Realism(room_size=4.9, room_size_spread=1.0)


def test_clean_is_todays_houses_byte_for_byte(tmp_path: Path) -> None:
    from mpchair.cli import main

    write_synthetic_houses(tmp_path / "api" / "r", 1, 4, realism=CLEAN)
    write_synthetic_houses(tmp_path / "api" / "h", 1, 4, layout="habitat", realism=CLEAN)
    assert _tree_digest(tmp_path / "api") == TODAYS_CLEAN_BYTES
    for layout, sub in (("release", "r"), ("habitat", "h")):
        with pytest.raises(SystemExit) as e:
            main(["synth", "--out", str(tmp_path / "cli" / sub), "--houses", "1", "--seed", "4", "--layout", layout,
                  "--realism", "clean"])  # fmt: skip
        assert e.value.code == 0
    assert _tree_digest(tmp_path / "cli") == TODAYS_CLEAN_BYTES


def test_same_seed_same_bytes_and_labels_stay_exact(tmp_path: Path) -> None:
    write_synthetic_houses(tmp_path / "a", 1, 9)
    write_synthetic_houses(tmp_path / "b", 1, 9)
    assert _tree_digest(tmp_path / "a") == _tree_digest(tmp_path / "b")
    write_synthetic_houses(tmp_path / "c", 1, 10)
    assert _tree_digest(tmp_path / "c") != _tree_digest(tmp_path / "a")
    # Every object's box is its true box: the same house without artifacts (same layout, same clutter) has it too.
    no_artifacts = Realism(**{k: getattr(DEFAULT, k) for k in ("room_size", "room_size_spread", "open_plan", "clutter",
                                                               "doors", "chair_mix")})  # the layout knobs only
    hid, hs, lv = plan_houses(1, 9)[0]
    real, plain = synthesize_house(hs, hid, levels=lv), synthesize_house(hs, hid, levels=lv, realism=no_artifacts)
    assert len(real.objects) == len(plain.objects) and len(real.faces) > 3 * len(plain.faces)
    for a, b in zip(real.objects, plain.objects):
        assert (a.raw_category, a.style) == (b.raw_category, b.style)
        np.testing.assert_array_equal(a.aligned_box, b.aligned_box)
    assert real.unlabelled_faces > plain.unlabelled_faces
    objects = real.objects + synthesize_house(*plan_houses(2, 9)[1][1:2], plan_houses(2, 9)[1][0]).objects
    assert "stool" in {o.style for o in objects if o.mpcat40_index == 3}  # a sixth chair kind
    assert {o.mpcat40_name for o in objects} >= {"plant", "shelving", "objects", "door", "cushion"}


def test_vertex_noise_moves_points_by_at_most_its_amplitude() -> None:
    amp = 0.015
    grid = Realism(surface_holes=1e-12)  # re-meshed shell, no other knob: the noise is the only difference
    a = synthesize_house(3, levels=1, realism=grid)
    b = synthesize_house(3, levels=1, realism=dataclasses.replace(grid, vertex_noise=amp))
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_array_equal(a.material_id, b.material_id)
    moved = np.linalg.norm(b.vertices - a.vertices, axis=1)
    assert moved.max() <= amp + 1e-9
    assert moved.max() > 0.8 * amp and np.median(moved) > 0.2 * amp  # and it is really there
    # Chairs stay inside their true boxes (grown by the slack the label filters' margin absorbs).
    for o in b.objects:
        if o.mpcat40_index == 3:
            np.testing.assert_array_equal(o.aligned_box, a.objects[o.index].aligned_box)


def test_hole_over_a_chair_makes_in_box_fraction_reject_a_box_the_clean_house_keeps(tmp_path: Path) -> None:
    holes = Realism(chair_holes=1.0)
    clean, holey = _read(tmp_path, "clean", 5, CLEAN), _read(tmp_path, "holey", 5, holes)
    chairs = [k for k, o in enumerate(clean.objects) if o.mpcat40_index == 3]
    for k in chairs:  # same objects, same true boxes
        np.testing.assert_allclose(holey.objects[k].aligned_box, clean.objects[k].aligned_box, atol=1e-6)
    rc_clean = rc_holey = None
    found = []
    floor_z = min(r.floor_z for r in clean.regions)
    for k in chairs:
        c = clean.objects[k].aligned_box
        if abs(c[2] - c[5] / 2 - floor_z) > 0.05:
            continue  # ground-level chairs only (the sensor height is above floor_z)
        for ang in np.linspace(0, 2 * np.pi, 8, endpoint=False):
            x, y = c[0] + 2.2 * np.cos(ang), c[1] + 2.2 * np.sin(ang)
            pose = _pose(x, y, floor_z + 1.25, ang + np.pi)
            a, rc_clean = _decide(clean, pose, rc_clean)
            if a[k][0] != "":
                continue
            b, rc_holey = _decide(holey, pose, rc_holey)
            if b[k][0] == "in_box_fraction":
                found.append((k, a[k], b[k]))
        if found:
            break
    assert found, "no frame where a chair hole rejects a box the clean house keeps"
    for _, kept, rejected in found:
        assert kept[3] >= 0.8 and rejected[3] < 0.8 and rejected[1] > 35


def test_chair_behind_a_table_loses_points_and_points_in_box_rejects_it() -> None:
    def scene(table: bool, bleed: bool):
        hb = HouseBuilder()
        hb.room(-1, -3, 8, 3)
        hb.chair(4.0, 0.0)  # 0.5 x 0.45 x 0.9 m
        if table:  # a table with a cloth to the floor, in front of the chair: it hides the chair completely
            hb.add_box((3.3, 0.0, 0.525), (0.6, 0.6, 1.05), category=TABLE)
        house = hb.build()
        if not bleed:
            return house
        # The chair's label bled onto the floor around it (the knob ``chair_holes``), as synthesize_house makes it.
        ring = bleed_rects(np.array([-0.25, -0.225]), np.array([0.25, 0.225]), (0.05, 0.05, 0.2, 0.2))
        v, f = floor_tiles(ring, 0.025)
        v = v + [4.0, 0.0, 0.0]
        chair = next(i for i, o in enumerate(house.objects) if o.mpcat40_index == CHAIR)
        return dataclasses.replace(
            house, vertices=np.vstack([house.vertices, v]), faces=np.vstack([house.faces, f + len(house.vertices)]),
            face_object=np.concatenate([house.face_object, np.full(len(f), chair)]),
            face_category=np.concatenate([house.face_category, np.full(len(f), CHAIR)]),
            face_segment=np.concatenate([house.face_segment, np.full(len(f), chair)]))  # fmt: skip

    pose = _pose(0.0, 0.0, 1.25, 0.0)
    open_view = _decide(scene(table=False, bleed=True), pose)[0]
    chair = next(iter(open_view))
    assert open_view[chair][0] == ""  # seen in full, the bleed is a small part of its pixels
    behind = _decide(scene(table=True, bleed=False), pose)[0][chair]
    assert behind[0] == "visible_pixels" and behind[1] <= 35  # hidden: too few pixels to count
    bled = _decide(scene(table=True, bleed=True), pose)[0][chair]
    assert bled[0] == "points_in_box", bled  # the bleed is seen (> 35 pixels), its box holds too few of them
    assert bled[1] > 35 and bled[2] < SENSOR.filters.min_points_in_box


def test_readers_read_every_file_of_realistic_houses_release_and_habitat_zipped(tmp_path: Path) -> None:
    rel, hab = tmp_path / "rel", tmp_path / "hab"
    ids = write_synthetic_houses(rel, 2, 12, zip_files=True)
    assert write_synthetic_houses(hab, 2, 12, layout="habitat", zip_files=True) == ids
    found_rel, found_hab = find_houses(rel), find_houses(hab)
    for hid, hs, lv in plan_houses(2, 12):
        syn = synthesize_house(hs, hid, levels=lv)
        a, b = read_house(found_rel[hid]), read_house(found_hab[hid])
        assert found_rel[hid].layout == "release" and found_hab[hid].layout == "habitat"
        assert a.warnings == () and len(a.objects) == len(syn.objects)
        for h in (a, b):
            np.testing.assert_array_equal(h.faces, syn.faces)
            np.testing.assert_array_equal(h.face_object, syn.segment_id)
            for o, g in zip(h.objects, syn.objects):
                np.testing.assert_allclose(o.aligned_box[:6], g.aligned_box[:6], atol=1e-5)
        assert a.unlabelled_faces == syn.unlabelled_faces > 0
        assert a.navmesh is None and b.navmesh is not None and len(b.navmesh.poly_vertices) > 0


def test_default_chair_mix_gives_the_originals_mean_box_on_every_seed() -> None:
    # What issue 27 targets is the mean of the *kept* boxes (tools/realism_calibration.py; slow test in
    # test_realism_calibration.py); this checks the chair mix behind it on the houses alone, 8 per seed as there.
    # Kept boxes are a few percent longer than the houses' chairs (long chairs are seen more often, from further),
    # so the houses' mean is held to 6 %, and every seed's to 4 % of the pool: the chaise quota keeps the mix steady.
    from mpchair.analysis.calibration import ORIGINAL

    means, styles, shares = [], set(), []
    for seed in range(6):
        boxes = []
        for hid, hs, lv in plan_houses(8, seed):
            chairs = [o for o in synthesize_house(hs, hid, levels=lv).objects if o.mpcat40_index == 3]
            boxes += [o.aligned_box[3:6] for o in chairs]
            styles |= {o.style for o in chairs}
            shares.append(sum(o.style == "lounge" for o in chairs) / len(chairs))
        means.append(np.mean(boxes, axis=0))
    pooled = np.mean(means, axis=0)
    np.testing.assert_allclose(pooled, ORIGINAL["lwh"], rtol=0.06)
    np.testing.assert_allclose(means, np.broadcast_to(pooled, (6, 3)), rtol=0.04)
    assert styles == {"dining", "armchair", "office", "folding", "lounge", "rocking", "stool"}
    assert 0.15 < np.median(shares) < 0.3 and max(shares) < 0.4  # chaise longues: about a quarter of every house's
