"""Bad input gives one clean InputError naming the file and line/record; the CLI turns it into exit status 2."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mpchair.cli import main
from mpchair.core.errors import InputError
from mpchair.matterport import read_house
from mpchair.matterport.housefile import parse_house_text
from mpchair.matterport.ply import encode_ply, read_ply

DATA = Path(__file__).parent / "data" / "matterport"
MINI = DATA / "v1" / "scans" / "MINI0000011" / "house_segmentations"
MINI_TEXT = (MINI / "MINI0000011.house").read_text()


def _house_with(tmp_path: Path, text: str) -> Path:
    folder = tmp_path / "h"
    shutil.copytree(MINI, folder)
    (folder / "MINI0000011.house").write_text(text)
    return folder


def _replace_line(prefix: str, new: str) -> str:
    lines = MINI_TEXT.splitlines()
    k = next(i for i, ln in enumerate(lines) if ln.startswith(prefix))
    lines[k] = new
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize(
    ("text", "line", "message"),
    [
        ("\n".join(MINI_TEXT.splitlines()[:-2]) + "\n", 16, "truncated file\\? H record says 3 segments, found 1"),
        (_replace_line("O  2", "O  2 0 2  2 3.5 0.4  1 0 0  0 1 0  0.8 0.3 0.4  0 0 0 0 0 0 0 0 0 0"), 15,
         "O record: has 26 tokens, expected 24"),
        (_replace_line("E  1", "E  1 1 1000002  0.5  3 3"), 17, "E record: has 7 tokens, expected 19"),
        (_replace_line("O  0", "O  0 0 0  1 1 nan  0 0 1  0.8 0.6 0  0.45 0.3 0.25"), 13,
         "O record: token 6 is 'nan', expected a finite number"),
        (_replace_line("V  2", "V  2 0  F  4 inf 0  0 0 1  0 0 0"), 8, "token 5 is 'inf'"),
        (_replace_line("C  1", "C  one  25 dining#chair  3 chair"), 11, "token 1 is 'one', expected an integer"),
        (_replace_line("O  1", "O  1 0 7  3 3 0.45  0 0 1  1 0 0  0.45 0.3 0.25"), 14, "category index 7"),
        (_replace_line("E  2", "E  2 9 1000003  0.9  2 3.5 0.4  1.2 3.2 0 2.8 3.8 0.8"), 18, "object index 9"),
        (_replace_line("L  0", "X  0  1  -  2 2 0  0 0 0  4 4 3"), 3, "unknown record letter 'X'"),
        ("ASCII 2.0\n" + "\n".join(MINI_TEXT.splitlines()[1:]), 1, "first line must be"),
        ("", 1, "empty .house file"),
    ],
)  # fmt: skip
def test_bad_house_records(tmp_path: Path, text: str, line: int, message: str) -> None:
    folder = _house_with(tmp_path, text)
    with pytest.raises(InputError, match=message) as e:
        read_house(folder)
    assert e.value.path == str(folder / "MINI0000011.house") and e.value.line == line
    assert "\n" not in str(e.value)


def test_portal_count_that_swallows_a_panorama_is_reported() -> None:
    text = (DATA / "v1/scans/PORTALS0011/PORTALS0011/house_segmentations/PORTALS0011.house").read_text()
    text = text.replace("2 2 8 2 2 2 2 2 1 1", "2 2 8 2 2 2 2 2 2 1", 1)  # H says 2 portals, the file has 1
    with pytest.raises(InputError, match="says 2 portals but only 1 precede this panorama line") as e:
        parse_house_text(text, "x.house")
    assert e.value.line == 17


def test_bad_ply_files(tmp_path: Path) -> None:
    good = encode_ply(np.zeros((4, 3)), np.array([[0, 1, 2], [0, 2, 3]]), [1, 2], [0, 0], [7, 7])
    with pytest.raises(InputError, match="shorter than its header says: element 'face' needs 50 bytes") as e:
        read_ply(good[:-10], "short.ply")
    assert str(e.value).startswith("short.ply:")
    with pytest.raises(InputError, match="shorter than its header says"):
        read_ply(good.replace(b"element face 2", b"element face 3"), "x.ply")
    with pytest.raises(InputError, match="missing 'ply' magic"):
        read_ply(b"PK\x03\x04", "x.ply")
    with pytest.raises(InputError, match="no 'end_header'"):
        read_ply(b"ply\nformat ascii 1.0\n", "x.ply")
    ascii_ply = encode_ply(np.zeros((4, 3)), np.array([[0, 1, 2]]), [1], [0], [7], ascii=True)
    with pytest.raises(InputError, match="face 0 has 4 vertices"):
        read_ply(ascii_ply.replace(b"\n3 0 1 2 ", b"\n4 0 1 2 "), "x.ply")
    with pytest.raises(InputError, match="face 0 references a vertex outside 0..3"):
        read_ply(encode_ply(np.zeros((4, 3)), np.array([[0, 1, 9]]), [1], [0], [7], normals=np.zeros((4, 3))), "x.ply")
    with pytest.raises(InputError, match="vertex 1 has a non-finite coordinate"):
        read_ply(encode_ply(np.array([[0, 0, 0], [np.nan, 0, 0], [1, 1, 1]]), np.array([[0, 1, 2]]), [1], [0], [7]))
    with pytest.raises(InputError, match="unknown PLY header line"):
        read_ply(good.replace(b"element vertex 4", b"elephant vertex 4"), "x.ply")
    with pytest.raises(InputError, match="property 'x' appears twice in element 'vertex'") as e:
        read_ply(good.replace(b"property float y", b"property float x", 1), "dup.ply")
    assert str(e.value).startswith("dup.ply:")


def test_missing_and_short_ply_in_a_house(tmp_path: Path) -> None:
    folder = _house_with(tmp_path, MINI_TEXT)
    (folder / "MINI0000011.ply").unlink()
    with pytest.raises(InputError, match="file not found") as e:
        read_house(folder)
    assert e.value.path == str(folder / "MINI0000011.ply")
    (folder / "MINI0000011.ply").write_bytes((MINI / "MINI0000011.ply").read_bytes()[:-40])
    with pytest.raises(InputError, match="PLY body is shorter"):
        read_house(folder)


def test_cli_reports_one_line_and_exit_2(tmp_path: Path, capsys) -> None:
    folder = _house_with(tmp_path, "\n".join(MINI_TEXT.splitlines()[:-2]) + "\n")
    with pytest.raises(SystemExit) as e:
        main(["houses", "--root", str(folder)])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith(f"error: {folder / 'MINI0000011.house'}:16: truncated file?")


_TOKENS = st.one_of(
    st.sampled_from(["0", "-1", "1e9", "nan", "inf", "-", "#", "x", "3.5", "", "P", "R", "1.1"]),
    st.text(alphabet="0123456789.-eE#abc", max_size=6),
)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    line=st.integers(0, len(MINI_TEXT.splitlines()) - 1),
    pos=st.integers(0, 40),
    op=st.sampled_from(["replace", "delete", "insert", "drop_line", "dup_line"]),
    tok=_TOKENS,
)
def test_fuzzed_house_lines_never_crash(line: int, pos: int, op: str, tok: str) -> None:
    lines = [ln.split() for ln in MINI_TEXT.splitlines()]
    toks = lines[line]
    k = min(pos, len(toks) - 1)
    if op == "replace":
        toks[k] = tok
    elif op == "delete":
        del toks[k]
    elif op == "insert":
        toks.insert(k, tok)
    elif op == "drop_line":
        del lines[line]
    else:
        lines.insert(line, list(toks))
    text = "\n".join(" ".join(t) for t in lines) + "\n"
    try:
        hf = parse_house_text(text, "fuzz.house")
    except InputError as e:
        assert str(e).startswith("fuzz.house") and "\n" not in str(e)
    else:
        assert len(hf.objects) == hf.header.n_objects and len(hf.segments) == hf.header.n_segments


@settings(max_examples=40, deadline=None)
@given(cut=st.integers(0, 400), flip=st.integers(0, 400), value=st.integers(0, 255))
def test_fuzzed_ply_bytes_never_crash(cut: int, flip: int, value: int) -> None:
    data = bytearray(encode_ply(np.eye(3), np.array([[0, 1, 2], [2, 1, 0]]), [1, 2], [0, 1], [7, 25]))
    if flip < len(data):
        data[flip] = value
    data = bytes(data[: len(data) - cut % len(data)])
    try:
        mesh = read_ply(data, "fuzz.ply")
    except InputError as e:
        assert str(e).startswith("fuzz.ply")
    else:
        assert mesh.faces.shape[1] == 3 and (mesh.faces < len(mesh.vertices)).all()
