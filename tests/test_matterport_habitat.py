"""habitat's Matterport3D layout (``mp3d/<id>/<id>_semantic.ply``, ``.house``, ``.navmesh``; ``mp3d_habitat.zip``)
read like its release-layout twin; discovery at every root level (issue 17.1); zip members read with a cap (zip bombs
refused); bad semantic meshes and frames give one clean error. All files are written in the real formats by
``mpchair.synth``."""

from __future__ import annotations

import json
import shutil
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest

from mpchair.cli import main
from mpchair.core.errors import InputError
from mpchair.geometry import mp3d_to_habitat
from mpchair.matterport import HouseWarning, find_houses, read_house
from mpchair.matterport.house import habitat_object_ids
from mpchair.matterport.housefile import format_house
from mpchair.matterport.ply import encode_ply, encode_semantic_ply, read_semantic_ply
from mpchair.synth import plan_houses, synthesize_house, write_house, write_synthetic_houses

SEED = 31


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    """One synthetic house written in both layouts (folders and zips) under separate roots."""
    root = tmp_path_factory.mktemp("twin")
    hid, hs, lv = plan_houses(1, SEED)[0]
    house = synthesize_house(hs, hid, levels=lv)
    for name, layout, zipped in [("rel", "release", False), ("relzip", "release", True), ("hab", "habitat", False),
                                 ("habzip", "habitat", True)]:  # fmt: skip
        write_house(root / name, house, zip_files=zipped, layout=layout)
    return root, house


def _run(args: list[str], capsys) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as e:
        main(args)
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


# ------------------------------------------------------------------------------------------------ the twin


def test_habitat_house_reads_exactly_like_its_release_twin(twin) -> None:
    root, syn = twin
    rel = read_house(find_houses(root / "rel")[syn.id])
    for name in ("hab", "habzip"):
        src = find_houses(root / name)[syn.id]
        assert src.layout == "habitat" and (src.zip_path is not None) == (name == "habzip")
        hab = read_house(src)
        assert hab.layout == "habitat" and rel.layout == "release"
        for field in ("vertices", "faces", "face_object", "face_category"):
            np.testing.assert_array_equal(getattr(hab, field), getattr(rel, field), err_msg=field)
        assert [o.id for o in hab.objects] == [o.id for o in rel.objects]
        np.testing.assert_array_equal(np.stack([o.aligned_box for o in hab.objects]),
                                      np.stack([o.aligned_box for o in rel.objects]))  # fmt: skip
        assert hab.label_mismatch_rate is None and rel.label_mismatch_rate > 0  # the release file's drift faces
        assert hab.navmesh is not None and rel.navmesh is None
    # The semantic mesh is the release mesh with fewer fields: 15-byte vertices, 17-byte faces, object_id = O index.
    data = (root / "hab" / "mp3d" / syn.id / f"{syn.id}_semantic.ply").read_bytes()
    body = data.index(b"end_header\n") + len(b"end_header\n")
    assert len(data) - body == 15 * len(syn.vertices) + 17 * len(syn.faces)
    mesh = read_semantic_ply(data, "x")
    np.testing.assert_array_equal(mesh.object_id, syn.segment_id)  # the construction's O index per face


def test_houses_lists_both_layouts_with_the_same_counts(twin, tmp_path: Path, capsys) -> None:
    root, syn = twin
    other = synthesize_house(5, "OTHERHOUSE1", levels=1)
    mixed = tmp_path / "mixed"
    write_house(mixed, syn)  # release layout ...
    write_house(mixed, syn, layout="habitat")  # ... and its habitat twin: release wins
    write_house(mixed / "deeper" / "data", other, layout="habitat", zip_files=True)
    code, out, _ = _run(["houses", "--root", str(mixed), "--json"], capsys)
    assert code == 0
    rows = {r["id"]: r for r in json.loads(out)["houses"]}
    assert {k: r["layout"] for k, r in rows.items()} == {syn.id: "release", "OTHERHOUSE1": "habitat"}
    assert rows[syn.id]["navmesh"] is None and rows["OTHERHOUSE1"]["label_mismatch_rate"] is None
    nav = rows["OTHERHOUSE1"]["navmesh"]
    assert nav["version"] == 1 and nav["islands"] >= nav["islands_sampled"] >= 1 and nav["walkable_area_m2"] > 10
    code, out, _ = _run(["houses", "--root", str(root / "habzip"), "--json"], capsys)
    hab = json.loads(out)["houses"][0]
    code, out, _ = _run(["houses", "--root", str(root / "rel"), "--json"], capsys)
    rel = json.loads(out)["houses"][0]
    same = ("id", "version", "levels", "regions", "objects", "faces", "vertices", "unlabelled_faces",
            "objects_by_category")  # fmt: skip
    assert {k: hab[k] for k in same} == {k: rel[k] for k in same}
    assert hab["unlabelled_faces"] == syn.unlabelled_faces and hab["faces"] == len(syn.faces)
    code, out, _ = _run(["houses", "--root", str(root / "hab")], capsys)
    assert code == 0 and f"{syn.id} (habitat): ASCII 1.1" in out and "label mismatch n/a" in out and "navmesh:" in out


def test_synth_habitat_layout_is_deterministic(tmp_path: Path, capsys) -> None:
    for run in ("a", "b"):
        code, out, _ = _run(["synth", "--out", str(tmp_path / run), "--houses", "2", "--seed", "3", "--layout",
                             "habitat", "--zip", "--json"], capsys)  # fmt: skip
        assert code == 0
    assert (tmp_path / "a" / "mp3d_habitat.zip").read_bytes() == (tmp_path / "b" / "mp3d_habitat.zip").read_bytes()
    with zipfile.ZipFile(tmp_path / "a" / "mp3d_habitat.zip") as zf:
        ids = json.loads(out)["houses"]
        assert sorted(zf.namelist()) == sorted(f"mp3d/{h}/{h}{s}" for h in ids
                                               for s in (".house", "_semantic.ply", ".navmesh"))  # fmt: skip


# ------------------------------------------------------------------------------------------------ root levels


def test_every_root_level_finds_the_houses(tmp_path: Path, capsys) -> None:
    rel, hab = tmp_path / "download", tmp_path / "habitat"
    ids = write_synthetic_houses(rel, 2, SEED)
    write_synthetic_houses(rel / "zipped", 1, SEED + 1, zip_files=True)
    write_synthetic_houses(hab, 2, SEED, layout="habitat", zip_files=True)
    write_synthetic_houses(hab / "data" / "scene_datasets", 2, SEED, layout="habitat")
    zipped = plan_houses(1, SEED + 1)[0][0]
    levels = {
        rel: ids + [zipped],  # the folder holding v1
        rel / "v1": ids,
        rel / "v1" / "scans": ids,
        rel / "v1" / "scans" / ids[0]: ids[:1],  # one scan folder
        rel / "v1" / "scans" / ids[0] / "house_segmentations": ids[:1],
        rel / "zipped" / "v1" / "scans" / zipped / "house_segmentations.zip": [zipped],  # one zip
        hab / "mp3d_habitat.zip": ids,
        hab / "data": ids,  # extracted, any depth
        hab / "data" / "scene_datasets" / "mp3d": ids,
        hab / "data" / "scene_datasets" / "mp3d" / ids[1]: ids[1:],
        hab / "data" / "scene_datasets" / "mp3d" / ids[1] / f"{ids[1]}.house": ids[1:],
    }
    for root, want in levels.items():
        assert sorted(find_houses(root)) == sorted(want), root
    layouts = {s.layout for s in find_houses(hab).values()}
    assert layouts == {"habitat"} and find_houses(hab)[ids[0]].zip_path is None  # extracted beats the zip
    code, out, _ = _run(["houses", "--root", str(rel / "v1"), "--json"], capsys)
    assert code == 0 and sorted(r["id"] for r in json.loads(out)["houses"]) == sorted(ids)


# ------------------------------------------------------------------------------------------------ zip bombs


def _bomb(path: Path, member: str, head: bytes, size: int) -> Path:
    """A zip whose ``member`` is ``head`` plus zeros up to ``size`` bytes (deflates ~1000:1)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        with zf.open(member, "w", force_zip64=True) as f:
            f.write(head)
            zero = bytes(1 << 20)
            left = size - len(head)
            while left > 0:
                f.write(zero[: min(left, len(zero))])
                left -= len(zero)
    return path


@pytest.mark.parametrize("layout", ["release", "habitat"])
def test_zip_bomb_members_are_refused_before_decompression(twin, tmp_path: Path, layout: str) -> None:
    root, syn = twin
    files = syn.files() if layout == "release" else syn.habitat_files()
    mesh = ".ply" if layout == "release" else "_semantic.ply"
    prefix = f"{syn.id}/house_segmentations/" if layout == "release" else f"mp3d/{syn.id}/"
    name = "house_segmentations.zip" if layout == "release" else "mp3d_habitat.zip"
    # A mesh member whose header declares the real house but that holds 64 MiB: 64 MiB more than the header needs.
    z = _bomb(tmp_path / "a" / name, f"{prefix}{syn.id}{mesh}", files[mesh], 64 << 20)
    with zipfile.ZipFile(z, "a") as zf:
        zf.writestr(f"{prefix}{syn.id}.house", files[".house"])
        for k, v in files.items():
            if k not in (mesh, ".house"):
                zf.writestr(f"{prefix}{syn.id}{k}", v)
    assert z.stat().st_size < len(files[mesh]) + (1 << 20)  # a ~0.1-0.4 MB zip
    tracemalloc.start()
    try:
        with pytest.raises(InputError, match=r"zip member is 67108864 bytes uncompressed but can need at most \d+ "
                                             r"\(zip bomb\?\); refused") as e:  # fmt: skip
            read_house(find_houses(z)[syn.id])
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert e.value.path == f"{z}:{prefix}{syn.id}{mesh}"
    assert peak < 16 << 20  # the 64 MiB were never decompressed
    # Text members have fixed caps (64 MiB for a .house).
    z2 = _bomb(tmp_path / "b" / name, f"{prefix}{syn.id}.house", files[".house"], (64 << 20) + 1)
    with zipfile.ZipFile(z2, "a") as zf:
        zf.writestr(f"{prefix}{syn.id}{mesh}", files[mesh])
    with pytest.raises(InputError, match="can need at most 67108864"):
        read_house(find_houses(z2)[syn.id])


# ------------------------------------------------------------------------------------------------ bad input


def _habitat_copy(root: Path, syn, tmp_path: Path) -> Path:
    folder = tmp_path / "mp3d" / syn.id
    shutil.copytree(root / "hab" / "mp3d" / syn.id, folder)
    return folder


def _set(data: bytes, at: int, new: bytes) -> bytes:
    return data[:at] + new + data[at + len(new) :]


def test_bad_semantic_meshes_give_one_clean_error(twin, tmp_path: Path) -> None:
    root, syn = twin
    folder = _habitat_copy(root, syn, tmp_path)
    ply = folder / f"{syn.id}_semantic.ply"
    good = ply.read_bytes()
    oid = habitat_object_ids(syn.house_file, syn.material_id)
    cases = [
        (good[:-5], r"PLY body is shorter than its header says: element 'face' needs"),
        (good + b"\x00" * 7, "PLY body is longer than its header says: 7 bytes after the last element"),
        (good.replace(b"property int object_id", b"property float object_id"), "'object_id' must be int, uint"),
        (_set(good, len(good) - 17 * len(syn.faces), b"\x04"), "face 0 has 4 vertices; only triangles"),
        (_set(good, len(good) - 17 * len(syn.faces) + 1, b"\xff\xff\xff\x7f"), r"face 0 references a vertex outside"),
        (encode_ply(syn.vertices, syn.faces, syn.material_id, syn.segment_id, syn.category_id),
         "semantic mesh lacks the per-face 'object_id' property"),
    ]  # fmt: skip
    for data, message in cases:
        ply.write_bytes(data)
        with pytest.raises(InputError, match=message) as e:
            read_house(folder)
        assert e.value.path == str(ply) and "\n" not in str(e.value)
    # ushort ids (Gibson/Replica-style) read the same; ids outside [0, #O) are unlabelled.
    ply.write_bytes(encode_semantic_ply(syn.vertices, syn.faces, np.where(oid < 0, 65535, oid), syn.colors,
                                        id_type="ushort"))  # fmt: skip
    with pytest.warns(HouseWarning, match=f"{int(np.sum(oid < 0))} faces have an object_id outside"):
        h = read_house(folder)
    np.testing.assert_array_equal(h.face_object, read_house(root / "hab" / "mp3d" / syn.id).face_object)


def test_object_ids_without_an_o_record_are_an_error(twin, tmp_path: Path) -> None:
    root, syn = twin
    folder = _habitat_copy(root, syn, tmp_path)
    # Renumber the last O record (and its E records) to 5000: O indices are no longer 0..#O-1, and the faces that
    # still carry the old index name no O record.
    last = syn.house_file.objects[-1]
    hf = syn.house_file
    objects = hf.objects[:-1] + (type(last)(5000, *[getattr(last, f) for f in list(last.__dataclass_fields__)[1:]]),)
    segments = tuple(type(e)(**{**e.__dict__, "object": 5000}) if e.object == last.index else e for e in hf.segments)
    (folder / f"{syn.id}.house").write_text(format_house(type(hf)(**{**hf.__dict__, "objects": objects,
                                                                     "segments": segments})))  # fmt: skip
    n = int(np.sum(syn.segment_id == last.index))
    with pytest.raises(InputError, match=f"face \\d+ has object_id {last.index} but the .house has no O record with "
                                         f"that index \\({n} faces like it\\)") as e:  # fmt: skip
        read_house(folder)
    assert e.value.path == str(folder / f"{syn.id}_semantic.ply")


def test_frame_check_converts_y_up_and_refuses_other_frames(twin, tmp_path: Path, capsys) -> None:
    root, syn = twin
    folder = _habitat_copy(root, syn, tmp_path)
    ply = folder / f"{syn.id}_semantic.ply"
    oid = habitat_object_ids(syn.house_file, syn.material_id)
    twin_house = read_house(root / "hab" / "mp3d" / syn.id)
    ply.write_bytes(encode_semantic_ply(mp3d_to_habitat(syn.vertices), syn.faces, oid, syn.colors))
    with pytest.warns(HouseWarning, match="habitat's y-up frame .* converted"):
        h = read_house(folder)
    np.testing.assert_allclose(h.vertices, twin_house.vertices, atol=1e-5)
    ply.write_bytes(encode_semantic_ply(syn.vertices + [40.0, 0.0, 0.0], syn.faces, oid, syn.colors))
    with pytest.raises(InputError, match=r"only \d+\.\d% of the vertices lie inside the .house H box grown by 0.5 m"):
        read_house(folder)
    code, out, err = _run(["houses", "--root", str(folder)], capsys)
    assert code == 2 and out == "" and err.count("\n") == 1 and err.startswith(f"error: {ply}: only ")
