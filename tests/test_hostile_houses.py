"""Hostile house inputs (issue 33, items 3, 4 and 7): encrypted or oddly compressed zip members, duplicated members,
house ids that are not file-name stems, an ASCII PLY with values past its body, a ``.house`` cut short, a navmesh of
coincident vertices. Each is one ``error: file: ...`` line and exit 2, or (the navmesh) a clean description."""

from __future__ import annotations

import json
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest

from mpchair.cli import main
from mpchair.core.errors import InputError
from mpchair.matterport import find_houses, read_house
from mpchair.matterport.navmesh import encode_navmesh

DATA = Path(__file__).parent / "data" / "matterport" / "v1" / "scans"
MINI = DATA / "MINI0000011" / "house_segmentations"
ASCII_HOUSE = DATA / "OLDASCII010" / "house_segmentations"


def run(capsys, *args) -> tuple[int, str]:
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in args])
    out = capsys.readouterr()
    return e.value.code, out.out + out.err


def _zip_of(path: Path, members: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return path


def _patch_headers(z: Path, member: str, local_at: int, central_at: int, value: int) -> None:
    """Overwrite a 2-byte field of ``member``'s local header (offset ``local_at``) and central directory entry
    (``central_at``): zipfile writes neither encrypted members nor unknown methods, so the test makes them."""
    raw = bytearray(z.read_bytes())
    name = member.encode()
    for sig, field_at, name_off in ((b"PK\x03\x04", local_at, 30), (b"PK\x01\x02", central_at, 46)):
        at = raw.find(sig)
        while at >= 0:
            if raw[at + name_off : at + name_off + len(name)] == name:
                raw[at + field_at : at + field_at + 2] = value.to_bytes(2, "little")
            at = raw.find(sig, at + 4)
    z.write_bytes(bytes(raw))


def _mini_members(prefix: str = "MINI0000011/house_segmentations/") -> dict[str, bytes]:
    return {prefix + p.name: p.read_bytes() for p in sorted(MINI.iterdir())}


def test_an_encrypted_member_is_refused_before_reading(tmp_path, capsys):
    ply = "MINI0000011/house_segmentations/MINI0000011.ply"
    z = _zip_of(tmp_path / "house_segmentations.zip", _mini_members())
    _patch_headers(z, ply, 6, 8, 0x1)  # general-purpose flags: bit 0, encrypted
    code, out = run(capsys, "houses", "--root", z)
    assert code == 2 and out.splitlines() == [f"error: {z}:{ply}: zip member is encrypted; refused (Matterport3D "
                                              "zips are not)"], out


def test_an_unknown_compression_method_is_refused(tmp_path, capsys):
    z = _zip_of(tmp_path / "house_segmentations.zip", _mini_members())
    name = "MINI0000011/house_segmentations/MINI0000011.house"
    _patch_headers(z, name, 8, 10, 99)  # compression method 99 (AES)
    code, out = run(capsys, "houses", "--root", z)
    assert code == 2 and len(out.splitlines()) == 1, out
    assert out.startswith(f"error: {z}:{name}: zip member uses compression method 99, not one of stored, "
                          "deflate, bzip2, lzma; refused"), out


def test_a_duplicated_member_is_refused(tmp_path):
    z = tmp_path / "house_segmentations.zip"
    _zip_of(z, _mini_members())
    with zipfile.ZipFile(z, "a") as zf, pytest.warns(UserWarning, match="Duplicate name"):
        zf.writestr("MINI0000011/house_segmentations/MINI0000011.house", b"ASCII 1.1\n")
    with pytest.raises(InputError, match="holds member 'MINI0000011/house_segmentations/MINI0000011.house' more "
                                         "than once"):
        find_houses(z)


@pytest.mark.parametrize("hid", ["bad\nid", "tab\tid", "--help", "..", "", "-x", "id with spaces"])
def test_house_ids_that_are_not_file_stems_are_refused_and_shown_escaped(tmp_path, capsys, hid):
    members = {f"scans/{hid}.house": (MINI / "MINI0000011.house").read_bytes(),
               f"scans/{hid}.ply": (MINI / "MINI0000011.ply").read_bytes()}
    z = _zip_of(tmp_path / "house_segmentations.zip", members)
    code, out = run(capsys, "houses", "--root", z)
    assert code == 2 and len(out.splitlines()) == 1, out
    assert f"{hid!r} is not a house id" in out


def test_an_ascii_ply_with_values_after_its_body_is_refused(tmp_path):
    folder = tmp_path / "h"
    shutil.copytree(ASCII_HOUSE, folder)
    read_house(find_houses(folder)["OLDASCII010"])  # the fixture itself reads
    with (folder / "OLDASCII010.ply").open("a") as f:
        f.write("7 7 7\n")
    with pytest.raises(InputError, match="OLDASCII010.ply: PLY body is longer than its header says: 3 values after "
                                         "the last element"):
        read_house(find_houses(folder)["OLDASCII010"])


@pytest.mark.parametrize("cut", [1, 10, 40])
def test_a_house_file_cut_short_is_refused(tmp_path, cut):
    folder = tmp_path / "h"
    shutil.copytree(MINI, folder)
    text = (MINI / "MINI0000011.house").read_bytes()
    (folder / "MINI0000011.house").write_bytes(text[:-cut])
    with pytest.raises(InputError, match=r"MINI0000011.house:\d+: .*(truncated|tokens)") as err:
        read_house(find_houses(folder)["MINI0000011"])
    assert "\n" not in str(err.value)


def test_houses_describes_a_navmesh_of_coincident_vertices(tmp_path, capsys):
    """Every vertex at one point: nothing is walkable, and ``mpchair houses`` says so instead of a traceback."""
    from mpchair.synth import plan_houses, synthesize_house, write_house

    hid, hs, lv = plan_houses(1, 5)[0]
    write_house(tmp_path, synthesize_house(hs, hid, levels=lv), layout="habitat")
    nav = next(tmp_path.rglob("*.navmesh"))
    nav.write_bytes(encode_navmesh(np.ones((4, 3)), np.array([[0, 1, 2, 3]])))
    code, out = run(capsys, "houses", "--root", tmp_path, "--json")
    assert code == 0, out
    (row,) = json.loads(out)["houses"]
    navmesh = row["navmesh"]
    assert navmesh["islands_sampled"] == 0 and navmesh["walkable_area_m2"] == 0.0


def test_a_warning_never_precedes_the_error_line(tmp_path, capsys):
    """The ASCII 1.0 house warns (no objects) and then fails generate: the output is the error line alone."""
    code, out = run(capsys, "generate", "--root", ASCII_HOUSE, "--house", "OLDASCII010", "--frames", "2", "--out",
                    tmp_path / "d")
    assert code == 2 and out.splitlines() == [f"error: {ASCII_HOUSE / 'OLDASCII010.house'}: house OLDASCII010 has "
                                              "no object of class chair (it has: no objects)"], out


def test_warnings_of_a_successful_run_are_one_line_each_after_its_output(tmp_path, capsys):
    code, out = run(capsys, "view-house", "--root", ASCII_HOUSE, "--house", "OLDASCII010", "--out", tmp_path / "h.png")
    lines = out.splitlines()
    assert code == 0 and lines[0].startswith("wrote ") and len(lines) == 2, out
    assert lines[1] == f"warning: {ASCII_HOUSE / 'OLDASCII010.house'}: no objects (ASCII 1.0); regions and floors only"
