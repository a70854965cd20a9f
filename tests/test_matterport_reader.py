"""The Matterport3D reader on hand-written trap files (tests/data/matterport) and on the format's building blocks.

Fixtures: ``MINI0000011`` is the format notes' section-8 example (plus a "desk and chairs" misc object, missing
trailing zeros, an unlabelled floor, one face whose segment_id disagrees, ``\\o`` in semseg.json);
``PORTALS0011`` (extracted inside its scan folder) has a portal, panoramas, images, a tilted object and a region
with height 0; ``gaps/GAPSPORTALS`` is the same house re-saved by GAPS (portal written as ``R``) in a bare folder;
``OLDASCII010`` is ASCII 1.0.
"""

from __future__ import annotations

import math
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mpchair.core.errors import InputError
from mpchair.matterport import (
    CHAIR,
    HouseWarning,
    aligned_box,
    find_houses,
    mpcat40_table,
    obb_from_aligned,
    objects_of,
    orthonormal_axes,
    read_house,
    resolve_categories,
    resolve_category,
)
from mpchair.matterport.jsonfiles import loads_lenient, read_fsegs, read_semseg
from mpchair.matterport.ply import encode_ply, read_ply

DATA = Path(__file__).parent / "data" / "matterport"
SCANS = DATA / "v1" / "scans"
MINI = SCANS / "MINI0000011" / "house_segmentations"
PORTALS = SCANS / "PORTALS0011" / "PORTALS0011" / "house_segmentations"


# ------------------------------------------------------------------------------------------------ discovery


def test_find_houses_accepts_download_root_scans_folder_and_house_folders() -> None:
    ids = ["MINI0000011", "OLDASCII010", "PORTALS0011"]
    assert list(find_houses(DATA)) == ["GAPSPORTALS", *ids]  # the folder holding v1 (and gaps/, any depth)
    assert list(find_houses(DATA / "v1")) == ids  # v1 itself
    assert list(find_houses(SCANS)) == ids  # scans/ folder
    assert list(find_houses(SCANS / "MINI0000011")) == ["MINI0000011"]  # scan folder, extracted from v1/scans
    assert list(find_houses(SCANS / "PORTALS0011")) == ["PORTALS0011"]  # extracted inside the scan folder
    assert list(find_houses(MINI)) == ["MINI0000011"]  # the house_segmentations folder itself
    assert list(find_houses(DATA / "gaps")) == ["GAPSPORTALS"]  # bare folder with <id>.house + <id>.ply
    assert list(find_houses(MINI / "MINI0000011.house")) == ["MINI0000011"]


def test_find_houses_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="house root not found"):
        find_houses(tmp_path / "missing")
    with pytest.raises(InputError, match="no house found"):
        find_houses(tmp_path)


def _zip_house(src: Path, hid: str, dest: Path) -> Path:
    """A house_segmentations.zip laid out like the download script's (members <id>/house_segmentations/<id>.*)."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(dest, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for p in sorted(src.iterdir()):
            zf.write(p, f"{hid}/house_segmentations/{p.name}")
    return dest


def test_zip_input_reads_like_the_extracted_folder(tmp_path: Path) -> None:
    z = _zip_house(MINI, "MINI0000011", tmp_path / "v1" / "scans" / "MINI0000011" / "house_segmentations.zip")
    _zip_house(PORTALS, "PORTALS0011", tmp_path / "v1" / "scans" / "PORTALS0011" / "house_segmentations.zip")
    found = find_houses(tmp_path)
    assert list(found) == ["MINI0000011", "PORTALS0011"]
    assert found["MINI0000011"].zip_path == z
    assert list(find_houses(z)) == ["MINI0000011"]  # the zip itself as the root
    a, b = read_house(found["MINI0000011"]), read_house(MINI)
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.face_object, b.face_object)
    assert [o.raw_category for o in a.objects] == [o.raw_category for o in b.objects]
    np.testing.assert_array_equal(np.stack([o.aligned_box for o in a.objects]),
                                  np.stack([o.aligned_box for o in b.objects]))  # fmt: skip
    assert [g.label for g in a.seg_groups] == [g.label for g in b.seg_groups]


def test_extracted_folder_wins_over_zip_in_the_same_scan(tmp_path: Path) -> None:
    scan = tmp_path / "MINI0000011"
    shutil.copytree(MINI, scan / "house_segmentations")
    _zip_house(MINI, "MINI0000011", scan / "house_segmentations.zip")
    assert find_houses(scan)["MINI0000011"].zip_path is None


# ------------------------------------------------------------------------------------------------ decoding


def test_doc_example_objects_boxes_and_categories() -> None:
    h = read_house(MINI)
    assert h.id == "MINI0000011" and h.version == "1.1"
    # '#' → space everywhere in the name, not only the first one.
    assert [o.raw_category for o in h.objects] == ["chair", "dining chair", "desk and chairs"]
    assert [o.mapping_index for o in h.objects] == [7, 25, 490]
    assert [(o.mpcat40_index, o.mpcat40_name) for o in h.objects] == [(3, "chair"), (3, "chair"), (40, "misc")]
    expect = [
        [1, 1, 0.45, 0.6, 0.5, 0.9, math.atan2(0.6, 0.8)],  # vertical axis listed first (a0)
        [3, 3, 0.45, 0.6, 0.5, 0.9, 0.0],
        [2, 3.5, 0.4, 1.6, 0.6, 0.8, 0.0],  # radii unsorted in a third-party file: still decoded by axis
    ]
    np.testing.assert_allclose(np.stack([o.aligned_box for o in h.objects]), expect, atol=1e-12)
    assert math.degrees(h.objects[0].aligned_box[6]) == pytest.approx(36.8699, abs=1e-4)
    np.testing.assert_allclose(h.objects[0].axes[2], [-0.6, 0.8, 0.0], atol=1e-12)  # a2 = a0 x a1
    assert [o.id for o in h.objects] == ["0_0_0", "0_0_1", "0_0_2"]
    assert [o.index for o in objects_of(h, "chair")] == [0, 1]
    assert [o.index for o in objects_of(h, 3)] == [0, 1]
    assert [o.index for o in objects_of(h, ["misc", "stool"])] == [2]
    assert h.objects_by_category() == {"chair": 2, "misc": 1}


def test_doc_example_face_chain_mismatch_and_regions() -> None:
    h = read_house(MINI)
    np.testing.assert_array_equal(h.face_object, [-1, -1, 0, 0, 1, 1, 2])
    np.testing.assert_array_equal(h.face_category, [-1, -1, 3, 3, 3, 3, 40])
    np.testing.assert_array_equal(h.face_segment, [0, 0, 1000001, 1000001, 1000002, 1000002, 1000003])
    assert h.unlabelled_faces == 2
    # Face 5 carries segment_id 0 although its material chain says object 1.
    assert h.label_mismatch_rate == pytest.approx(1 / 7)
    assert h.warnings == ()
    (r,) = h.regions
    assert (r.label, r.label_name, r.level, r.height, r.floor_z) == ("d", "dining room", 0, 2.6, 0.0)
    np.testing.assert_array_equal(r.floor_polygon, [[0, 0], [4, 0], [4, 4], [0, 4]])
    (lv,) = h.levels
    assert lv.regions == (0,)
    np.testing.assert_array_equal(h.bbox, [0, 0, 0, 4, 4, 3])
    # semseg.json has an invalid "\o" escape; the label keeps its backslash.
    assert [g.label for g in h.seg_groups] == ["chair", "dining chair", "desk and chairs \\other room"]
    assert [g.segments for g in h.seg_groups] == [(1000001,), (1000002,), (1000003,)]


def test_portals_panoramas_images_tilt_and_height_fallback() -> None:
    with pytest.warns(HouseWarning, match="tilted 20.0 deg"):
        h = read_house(SCANS / "PORTALS0011")
    (p,) = h.portals
    assert (p.index, p.region0, p.region1, p.label) == (0, 0, 1, "door")
    np.testing.assert_array_equal(p.bbox, [3.95, 1.5, 0, 4.05, 2.4, 2.05])
    assert [(q.name, q.index, q.region) for q in h.panoramas] == [
        ("aac9edb8b1c845bc8450c8b68ab24bef", 0, 0), ("0f37bd0737e349de9d536263a4bdd60d", 1, 1)]  # fmt: skip
    assert [(i.name, i.camera_index, i.yaw_index, i.width, i.height) for i in h.images] == [
        ("aac9edb8b1c845bc8450c8b68ab24bef_i0_0.jpg", 0, 0, 1280, 1024),
        ("0f37bd0737e349de9d536263a4bdd60d_i1_2.jpg", 1, 2, 1280, 1024)]  # fmt: skip
    np.testing.assert_array_equal(h.images[1].extrinsics[:, 3], [6, 2, 1.6, 1])
    np.testing.assert_array_equal(h.images[0].intrinsics, [[1075, 0, 629], [0, 1075, 511], [0, 0, 1]])
    assert [r.height for r in h.regions] == [2.6, pytest.approx(2.8)]  # 0 → AABB zmax - position z
    assert h.levels[0].label == "level 0"
    chair, stool = h.objects
    assert chair.tilt_deg == pytest.approx(20.0, abs=1e-5) and any("tilted" in w for w in h.warnings)
    np.testing.assert_allclose(chair.aligned_box, [2, 2, 0.5, 0.6, 0.5, 1.0, 0.0], atol=1e-6)
    assert (stool.raw_category, stool.mpcat40_name) == ("bar stool", "stool")  # a stool is not a chair
    np.testing.assert_allclose(stool.aligned_box, [6, 2, 0.45, 0.4, 0.4, 0.7, 0.0], atol=1e-12)
    np.testing.assert_array_equal(h.face_object, [0, 1, -1])
    np.testing.assert_array_equal(h.face_category, [3, 19, -1])
    assert h.label_mismatch_rate == 0.0
    assert [o.index for o in objects_of(h, "chair")] == [0]


def test_gaps_resaved_portals_as_r_lines() -> None:
    with pytest.warns(HouseWarning):
        g = read_house(DATA / "gaps")
    with pytest.warns(HouseWarning):
        p = read_house(SCANS / "PORTALS0011")
    assert len(g.regions) == 2 and len(g.portals) == 1 and len(g.panoramas) == 2
    assert (g.portals[0].region0, g.portals[0].region1) == (0, 1)
    np.testing.assert_array_equal(g.portals[0].bbox, p.portals[0].bbox)
    assert [q.name for q in g.panoramas] == [q.name for q in p.panoramas]


def test_ascii_10_reads_regions_and_floors_and_says_no_objects() -> None:
    with pytest.warns(HouseWarning, match="no objects"):
        h = read_house(SCANS / "OLDASCII010")
    assert h.version == "1.0" and h.objects == () and h.portals == ()
    (r,) = h.regions
    assert r.label_name == "bedroom"
    assert r.height == pytest.approx(2.59)  # no height in 1.0: AABB zmax - position z
    np.testing.assert_array_equal(r.floor_polygon, [[-1, -1], [3, -1], [3, 3], [-1, 3]])
    np.testing.assert_array_equal(h.bbox, [-1, -1, 0, 3, 3, 2.6])
    assert h.unlabelled_faces == 2


# ------------------------------------------------------------------------------------------------ building blocks


def test_json_escapes_are_tolerated_and_valid_ones_kept() -> None:
    assert loads_lenient(b'{"l": "wall \\other room"}') == {"l": "wall \\other room"}
    assert loads_lenient(b'{"l": "a\\\\o \\u00e9 \\n \\/"}') == {"l": "a\\o \u00e9 \n /"}
    assert loads_lenient(b'{"l": "x \\q \\utility"}') == {"l": "x \\q \\utility"}
    with pytest.raises(InputError, match="invalid JSON"):
        loads_lenient(b'{"l": ', "f.json")
    data = b'{"sceneId": "x", "segIndices": [3, -1, 7]}'
    np.testing.assert_array_equal(read_fsegs(data), [3, -1, 7])
    # Fallback path (a key before the list that is not plain integers) gives the same answer.
    np.testing.assert_array_equal(read_fsegs(b'{"segIndices": [3, -1, 7], "params": {"k": "\\o"}}'), [3, -1, 7])
    with pytest.raises(InputError, match="segIndices"):
        read_fsegs(b'{"other": 1}', "f.json")
    with pytest.raises(InputError, match="must hold integers"):
        read_fsegs(b'{"segIndices": [1, 2.5]}', "f.json")  # never truncated silently
    with pytest.raises(InputError, match="segGroups"):
        read_semseg(b"[]", "s.json")


def test_ply_binary_ascii_and_big_endian_agree() -> None:
    rng = np.random.default_rng(0)
    v = rng.uniform(-5, 5, (50, 3)).astype(np.float32).astype(np.float64)
    f = rng.integers(0, 50, (80, 3))
    m, s, c = rng.integers(-1, 10**6, 80), rng.integers(-1, 40, 80), rng.integers(-1, 1660, 80)
    binary = read_ply(encode_ply(v, f, m, s, c))
    ascii_ = read_ply(encode_ply(v, f, m, s, c, ascii=True))
    for mesh in (binary, ascii_):
        np.testing.assert_array_equal(mesh.vertices, v)
        np.testing.assert_array_equal(mesh.faces, f)
        np.testing.assert_array_equal(mesh.material_id, m)
        np.testing.assert_array_equal(mesh.segment_id, s)
        np.testing.assert_array_equal(mesh.category_id, c)
    vd = np.zeros(50, dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4")])
    vd["x"], vd["y"], vd["z"] = v.T
    fd = np.zeros(80, dtype=[("n", "u1"), ("v", ">i4", (3,)), ("material_id", ">i4")])
    fd["n"], fd["v"], fd["material_id"] = 3, f, m
    header = (b"ply\nformat binary_big_endian 1.0\nelement vertex 50\nproperty float x\nproperty float y\n"
              b"property float z\nelement face 80\nproperty list uchar int vertex_index\nproperty int material_id\n"
              b"end_header\n")  # fmt: skip
    big = read_ply(header + vd.tobytes() + fd.tobytes())
    np.testing.assert_array_equal(big.vertices, v)
    np.testing.assert_array_equal(big.faces, f)
    np.testing.assert_array_equal(big.material_id, m)
    assert big.segment_id is None and big.category_id is None


def test_release_ply_header_and_record_sizes() -> None:
    data = encode_ply(np.zeros((3, 3)), np.array([[0, 1, 2]]), [5], [0], [7])
    head, body = data.split(b"end_header\n")
    assert head.splitlines()[1] == b"format binary_little_endian 1.0"
    assert b"property list uchar int vertex_indices\nproperty int material_id\nproperty int segment_id\n" in head
    assert len(body) == 3 * 35 + 25  # packed 35-byte vertices, 25-byte faces


def test_categories_table_and_selection() -> None:
    table = mpcat40_table()
    assert len(table) == 42 and table[0].name == "void" and table[40].name == "misc" and table[41].name == "unlabeled"
    assert CHAIR == 3 == resolve_category("chair") == resolve_category("Chair") == resolve_category("3")
    assert (resolve_category("sofa"), resolve_category("stool"), resolve_category("seating")) == (10, 19, 34)
    assert resolve_category("tv monitor") == 22
    assert resolve_categories(["chair", 19]) == frozenset({3, 19})
    with pytest.raises(InputError, match="unknown mpcat40 class"):
        resolve_category("armchair")  # a raw category, not an mpcat40 class
    with pytest.raises(InputError, match="outside"):
        resolve_category(42)


def test_aligned_box_rules() -> None:
    # Up axis found wherever the radius sort put it; l/w from the two horizontal axes; yaw modulo pi.
    s2 = math.sqrt(0.5)
    for axes, radii, expect in [
        ([[0, 0, 1], [s2, s2, 0], [-s2, s2, 0]], [0.5, 0.4, 0.3], [0.8, 0.6, 1.0, math.pi / 4]),
        ([[s2, s2, 0], [0, 0, 1], [s2, -s2, 0]], [0.5, 0.4, 0.3], [1.0, 0.6, 0.8, math.pi / 4]),
        ([[-1, 0, 0], [0, -1, 0], [0, 0, 1]], [0.5, 0.4, 0.3], [1.0, 0.8, 0.6, 0.0]),  # direction (-1, 0) → yaw 0
        ([[0, 1, 0], [1, 0, 0], [0, 0, -1]], [0.5, 0.4, 0.3], [1.0, 0.8, 0.6, -math.pi / 2]),  # pi/2 wraps to -pi/2
    ]:
        box, tilt = aligned_box([1, 2, 3], np.array(axes, float), np.array(radii))
        np.testing.assert_allclose(box, [1, 2, 3, *expect], atol=1e-12)
        assert tilt == pytest.approx(0.0, abs=1e-6)
    ax = orthonormal_axes([0, 0, 2], [1, 0, 0.5])  # a1 is made orthogonal to a0 and normalised
    np.testing.assert_allclose(ax @ ax.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(ax[1], [1, 0, 0], atol=1e-12)


@settings(max_examples=100, deadline=None)
@given(
    st.floats(-50, 50), st.floats(-50, 50), st.floats(-5, 5),
    st.floats(0.05, 3), st.floats(0.05, 3), st.floats(0.05, 3), st.floats(-10, 10),
)  # fmt: skip
def test_obb_round_trip_recovers_any_yaw_only_box(x, y, z, a, b, h, yaw) -> None:
    l, w = max(a, b), min(a, b)
    center, axes, radii = obb_from_aligned(np.array([x, y, z, l, w, h, yaw]))
    assert radii[0] >= radii[1] >= radii[2]  # GAPS order
    np.testing.assert_allclose(np.cross(axes[0], axes[1]), axes[2], atol=1e-12)
    box, tilt = aligned_box(center, axes, radii)
    np.testing.assert_allclose(box[:6], [x, y, z, l, w, h], atol=1e-9)
    assert -math.pi / 2 <= box[6] < math.pi / 2
    if l - w > 1e-9:  # a square footprint has no long side
        d = (box[6] - yaw + math.pi / 2) % math.pi - math.pi / 2
        assert abs(d) < 1e-9
