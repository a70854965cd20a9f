"""KITTI readers and writers: round trips, exact layouts, and malformed input named by file and line."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from PIL import Image

from mpchair.core.errors import InputError
from mpchair.kitti import (
    Calib,
    Labels,
    format_calib,
    frame_paths,
    read_calib,
    read_image_size,
    read_imageset,
    read_labels,
    read_velodyne,
    to_4x4,
    write_calib,
    write_imageset,
    write_labels,
    write_velodyne,
)

HYP = settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)


def make_calib(rng: np.random.Generator) -> Calib:
    return Calib(
        P0=rng.normal(size=(3, 4)),
        P1=rng.normal(size=(3, 4)),
        P2=rng.normal(size=(3, 4)) * 700,
        P3=rng.normal(size=(3, 4)),
        R0_rect=rng.normal(size=(3, 3)),
        Tr_velo_to_cam=rng.normal(size=(3, 4)),
        Tr_imu_to_velo=rng.normal(size=(3, 4)),
    )


def raises_at(path: Path, line: int | None, match: str):
    """Context: an InputError whose message starts with ``path:line:`` and contains ``match``."""
    where = f"{path}:{line}: " if line is not None else f"{path}: "

    class _Ctx:
        def __enter__(self):
            self.cm = pytest.raises(InputError, match=match)
            self.info = self.cm.__enter__()
            return self.info

        def __exit__(self, *exc):
            ok = self.cm.__exit__(*exc)
            assert str(self.info.value).startswith(where), str(self.info.value)
            assert self.info.value.path == str(path) and self.info.value.line == line
            return ok

    return _Ctx()


# --------------------------------------------------------------------------------------------------------- calib
def test_calib_round_trip_and_layout(tmp_path):
    calib = make_calib(np.random.default_rng(0))
    path = tmp_path / "c.txt"
    write_calib(path, calib)
    back = read_calib(path)
    for key in ("P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo"):
        np.testing.assert_array_equal(getattr(back, key), getattr(calib, key))  # bit for bit
    lines = path.read_text().split("\n")
    # OpenPCDet reads by line index: P2 on line 3, R0_rect on 5, Tr_velo_to_cam on 6; single spaces only.
    assert [ln.split(":")[0] for ln in lines[:7]] == [
        "P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo"
    ]  # fmt: skip
    assert lines[7:] == ["", ""]
    assert all("  " not in ln and "\t" not in ln for ln in lines)
    assert [len(ln.split()) for ln in lines[:7]] == [13, 13, 13, 13, 10, 13, 13]
    write_calib(path, back)  # re-writing what was read changes nothing
    assert format_calib(read_calib(path)) == path.read_text()


def test_calib_any_key_order_blank_lines_and_extra_keys(tmp_path):
    calib = make_calib(np.random.default_rng(1))
    lines = format_calib(calib).strip().split("\n")
    path = tmp_path / "c.txt"
    path.write_text("\n\n" + "\n\n".join(reversed(lines)) + "\nExtra: 1 2 3")  # no final newline either
    assert read_calib(path) == calib


def test_calib_helpers():
    calib = make_calib(np.random.default_rng(2))
    np.testing.assert_array_equal(to_4x4(calib.R0_rect)[3], [0, 0, 0, 1])
    np.testing.assert_array_equal(to_4x4(calib.R0_rect)[:3, 3], [0, 0, 0])
    np.testing.assert_allclose(calib.velo_to_rect(), to_4x4(calib.R0_rect) @ to_4x4(calib.Tr_velo_to_cam))
    np.testing.assert_allclose(calib.rect_to_velo() @ calib.velo_to_rect(), np.eye(4), atol=1e-9)
    pts = np.array([[1.0, 2.0, 10.0], [-3.0, 0.5, 20.0]])
    uvw = np.c_[pts, np.ones(2)] @ calib.P2.T
    np.testing.assert_allclose(calib.rect_to_image(pts), uvw[:, :2] / uvw[:, 2:])
    with pytest.raises(ValueError, match="P2"):
        Calib(**{**{k: getattr(calib, k) for k in ("P0", "P1", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo")},
                 "P2": np.zeros((3, 3))})  # fmt: skip
    with pytest.raises(ValueError):
        calib.P2[0, 0] = 1.0  # frozen arrays


def _swap_first(line: str, token: str) -> str:
    key, values = line.split(": ")
    return key + ": " + " ".join([token, *values.split(" ")[1:]])


@pytest.mark.parametrize(
    "edit, line, match",
    [
        (lambda ls: ls[:4] + ls[5:], None, "missing calib key.*R0_rect"),
        (lambda ls: ls[:2] + [ls[2] + " 7.0"] + ls[3:], 3, "P2 has 13 values, expected 12"),
        (lambda ls: ls[:4] + ["R0_rect: 1 0 0 0 1 0 0 0"] + ls[5:], 5, "R0_rect has 8 values, expected 9"),
        (lambda ls: ls[:5] + [_swap_first(ls[5], "abc")] + ls[6:], 6, "Tr_velo_to_cam: 'abc' is not a number"),
        (lambda ls: ls[:1] + [_swap_first(ls[1], "nan")] + ls[2:], 2, "P1: 'nan' is not a finite"),
        (lambda ls: ls[:6] + [_swap_first(ls[6], "-inf")] + ls[7:], 7, "'-inf' is not a finite"),
        (lambda ls: ls + [ls[0]], 8, "duplicate key 'P0'"),
        (lambda ls: ["P0 1 2 3"] + ls[1:], 1, "expected 'KEY: values'"),
    ],
)
def test_calib_malformed(tmp_path, edit, line, match):
    lines = format_calib(make_calib(np.random.default_rng(3))).strip().split("\n")
    path = tmp_path / "bad_calib.txt"
    path.write_text("\n".join(edit(lines)) + "\n")
    with raises_at(path, line, match):
        read_calib(path)


def test_calib_missing_file(tmp_path):
    with raises_at(tmp_path / "nope.txt", None, "not found"):
        read_calib(tmp_path / "nope.txt")


# -------------------------------------------------------------------------------------------------------- labels
def make_labels(rng: np.random.Generator, n: int, dontcare: int = 0, score: bool = False) -> Labels:
    names = np.array(["Car", "Chair", "Pedestrian"])[rng.integers(0, 3, n)].tolist() + ["DontCare"] * dontcare
    m = n + dontcare
    r2 = lambda a: np.round(a, 2)  # noqa: E731 - ground truth has 2 decimals
    labels = Labels(
        names=np.array(names),
        truncated=r2(rng.uniform(0, 1, m)),
        occluded=rng.integers(0, 4, m),
        alpha=r2(rng.uniform(-3.14, 3.14, m)),
        bbox=r2(rng.uniform(0, 1000, (m, 4))),
        dims_hwl=r2(rng.uniform(0.3, 5, (m, 3))),
        location=r2(rng.uniform(-40, 40, (m, 3))),
        rotation_y=r2(rng.uniform(-3.14, 3.14, m)),
        score=np.round(rng.uniform(0, 1, m), 4) if score else None,
    )
    return labels


def _invalidate_dontcare(labels: Labels) -> Labels:
    """What reading back a DontCare row gives: the devkit's invalid values, the bbox kept."""
    dc = labels.dontcare_mask()
    f = {k: np.array(getattr(labels, k)) for k in ("truncated", "occluded", "alpha", "dims_hwl", "location",
                                                   "rotation_y")}  # fmt: skip
    f["truncated"][dc], f["occluded"][dc], f["alpha"][dc] = -1, -1, -10
    f["dims_hwl"][dc], f["location"][dc], f["rotation_y"][dc] = -1, -1000, -10
    return Labels(names=labels.names, bbox=labels.bbox, score=labels.score, **f)


def test_labels_round_trip_ground_truth_with_dontcare_last(tmp_path):
    rng = np.random.default_rng(4)
    objs, dcs = make_labels(rng, 5), make_labels(rng, 0, dontcare=3)
    mixed = Labels.concatenate([dcs[:1], objs[:2], dcs[1:], objs[2:]])  # DontCare in the middle on purpose
    path = tmp_path / "000007.txt"
    write_labels(path, mixed)
    text = path.read_text()
    rows = text.split("\n")
    assert rows[-1] == "" and "" not in rows[:-1]
    assert [r.split(" ")[0] for r in rows[:-1]][5:] == ["DontCare"] * 3  # written last
    assert all(len(r.split(" ")) == 15 for r in rows[:-1])
    assert rows[5].split(" ")[1:4] == ["-1", "-1", "-10"] and rows[5].split(" ")[8:] == [
        "-1", "-1", "-1", "-1000", "-1000", "-1000", "-10"
    ]  # fmt: skip
    back = read_labels(path)
    expected = _invalidate_dontcare(Labels.concatenate([objs, dcs]))
    assert back == expected
    assert back.score is None and len(back) == 8
    assert len(back.dontcare()) == 3 and len(back.objects()) == 5
    assert back[back.names == "Car"] == back.with_names("Car")


def test_labels_round_trip_results_with_score(tmp_path):
    labels = make_labels(np.random.default_rng(5), 6, score=True)
    path = tmp_path / "r.txt"
    write_labels(path, labels)
    rows = path.read_text().splitlines()
    assert all(len(r.split(" ")) == 16 for r in rows)
    assert rows[0].split(" ")[1].count(".") == 1 and len(rows[0].split(" ")[1].split(".")[1]) == 4  # 4 decimals
    back = read_labels(path)
    np.testing.assert_allclose(back.score, labels.score, atol=5e-5)
    np.testing.assert_allclose(back.location, labels.location, atol=5e-5)
    assert back.names.tolist() == labels.names.tolist()


def test_labels_precision_and_exact_row(tmp_path):
    labels = Labels(
        names=["Chair"], truncated=[0.123456], occluded=[1], alpha=[-0.0001], bbox=[[1, 2, 3, 4.005]],
        dims_hwl=[[0.9, 0.5, 0.6]], location=[[1.5, 0.2, 7.25]], rotation_y=[3.14159],
    )  # fmt: skip
    path = tmp_path / "one.txt"
    write_labels(path, labels)
    assert path.read_text() == "Chair 0.12 1 0.00 1.00 2.00 3.00 4.00 0.90 0.50 0.60 1.50 0.20 7.25 3.14\n"
    write_labels(path, labels, precision=3)
    assert path.read_text() == "Chair 0.123 1 0.000 1.000 2.000 3.000 4.005 0.900 0.500 0.600 1.500 0.200 7.250 3.142\n"


@given(
    data=st.data(),
    n=st.integers(0, 6),
)
@HYP
def test_labels_round_trip_property(tmp_path, data, n):
    def col(shape):
        return data.draw(arrays(np.float64, shape, elements=finite))

    labels = Labels(
        names=np.array(data.draw(st.lists(st.sampled_from(["Car", "Chair", "Sofa"]), min_size=n, max_size=n))),
        truncated=col(n), occluded=data.draw(arrays(np.int64, n, elements=st.integers(-1, 3))), alpha=col(n),
        bbox=col((n, 4)), dims_hwl=col((n, 3)), location=col((n, 3)), rotation_y=col(n),
        score=col(n) if data.draw(st.booleans()) else None,
    )  # fmt: skip
    path = tmp_path / "p.txt"
    write_labels(path, labels, precision=6)
    back = read_labels(path)
    if n == 0:
        assert len(back) == 0
        return
    assert back.names.tolist() == labels.names.tolist()
    assert (back.score is None) == (labels.score is None)
    for key in ("truncated", "alpha", "bbox", "dims_hwl", "location", "rotation_y"):
        np.testing.assert_allclose(getattr(back, key), getattr(labels, key), atol=5.1e-7, rtol=0)
    np.testing.assert_array_equal(back.occluded, labels.occluded)


def test_labels_empty_file_and_names_kept(tmp_path):
    path = tmp_path / "e.txt"
    path.write_text("")
    assert len(read_labels(path)) == 0
    path.write_text("\n\n")
    assert len(read_labels(path)) == 0
    path.write_text("car 0 0 0 1 2 3 4 1 1 1 0 0 5 0\n")  # names are kept as written, no case folding
    assert read_labels(path).names.tolist() == ["car"]
    write_labels(path, Labels.empty())
    assert path.read_text() == ""


def test_labels_writer_refuses_nan(tmp_path):
    labels = make_labels(np.random.default_rng(6), 2)
    bad = Labels(**{**{k: getattr(labels, k) for k in ("names", "truncated", "occluded", "bbox", "dims_hwl",
                                                     "location", "rotation_y")}, "alpha": [0.0, np.nan]})  # fmt: skip
    with pytest.raises(ValueError, match="alpha"):
        write_labels(tmp_path / "x.txt", bad)
    assert not (tmp_path / "x.txt").exists() and os.listdir(tmp_path) == []


GOOD = "Car 0.00 0 -1.57 599.41 156.40 629.75 189.25 2.85 2.63 12.34 0.47 1.49 69.44 -1.56"


@pytest.mark.parametrize(
    "rows, line, match",
    [
        ([GOOD, GOOD + " 0.5"], 2, "16 columns but line 1 has 15"),
        ([GOOD + " 0.5", "", GOOD], 3, "15 columns but line 1 has 16"),
        ([GOOD, GOOD.rsplit(" ", 1)[0]], 2, "14 columns, expected 15"),
        ([GOOD + " 1 2"], 1, "17 columns"),
        ([GOOD.replace("599.41", "x599")], 1, "column 5: 'x599' is not a number"),
        ([GOOD, GOOD.replace("69.44", "nan")], 2, "column 14: 'nan' is not a finite"),
        ([GOOD.replace("inf", "").replace("-1.56", "inf")], 1, "column 15"),
        ([GOOD.replace(" 0 -1.57", " 1.5 -1.57")], 1, "occluded"),
    ],
)
def test_labels_malformed(tmp_path, rows, line, match):
    path = tmp_path / "bad_label.txt"
    path.write_text("\n".join(rows) + "\n")
    with raises_at(path, line, match):
        read_labels(path)


# ------------------------------------------------------------------------------------------------------ velodyne
@given(points=arrays(np.float32, st.tuples(st.integers(0, 50), st.just(4)),
                     elements=st.floats(-100, 100, width=32)))  # fmt: skip
@HYP
def test_velodyne_round_trip(tmp_path, points):
    path = tmp_path / "v.bin"
    write_velodyne(path, points)
    assert path.stat().st_size == points.size * 4
    back = read_velodyne(path)
    assert back.dtype == np.float32 and back.shape == points.shape
    np.testing.assert_array_equal(back, points)


def test_velodyne_layout_is_little_endian_float32(tmp_path):
    path = tmp_path / "v.bin"
    write_velodyne(path, np.array([[1.0, -2.0, 0.5, 0.25]]))  # float64 input is cast
    assert path.read_bytes() == np.array([1.0, -2.0, 0.5, 0.25], dtype="<f4").tobytes()
    assert read_velodyne(path).tolist() == [[1.0, -2.0, 0.5, 0.25]]
    with pytest.raises(ValueError):
        write_velodyne(path, np.zeros((3, 3)))


def test_velodyne_malformed(tmp_path):
    path = tmp_path / "bad.bin"
    path.write_bytes(b"\0" * 36)
    with raises_at(path, None, "36 bytes is not a multiple of 16"):
        read_velodyne(path)
    with raises_at(tmp_path / "missing.bin", None, "not found"):
        read_velodyne(tmp_path / "missing.bin")


# ----------------------------------------------------------------------------------------------------- imagesets
@given(ids=st.lists(st.integers(0, 999999), unique=True, max_size=30))
@HYP
def test_imageset_round_trip(tmp_path, ids):
    path = tmp_path / "train.txt"
    write_imageset(path, ids)
    assert read_imageset(path) == [f"{i:06d}" for i in ids]
    assert path.read_text() == "".join(f"{i:06d}\n" for i in ids)


def test_imageset_tolerates_blank_lines_and_no_final_newline(tmp_path):
    path = tmp_path / "val.txt"
    path.write_text("000001\n\n000003\n  000002  \n000010")
    assert read_imageset(path) == ["000001", "000003", "000002", "000010"]
    with pytest.raises(ValueError):
        write_imageset(path, ["12345"])
    with pytest.raises(ValueError):
        write_imageset(path, ["000001", "000001"])


@pytest.mark.parametrize(
    "text, line, match",
    [
        ("000001\n12345\n", 2, "'12345' is not a 6-digit"),
        ("000001\n\n0000012\n", 3, "'0000012'"),
        ("abcdef\n", 1, "'abcdef'"),
        ("000001\n000002 x\n", 2, "6-digit"),
        ("000001\n000002\n000001\n", 3, "repeated .first on line 1"),
    ],
)
def test_imageset_malformed(tmp_path, text, line, match):
    path = tmp_path / "bad_split.txt"
    path.write_text(text)
    with raises_at(path, line, match):
        read_imageset(path)


# -------------------------------------------------------------------------------------------------------- layout
def test_frame_paths_and_image_size(tmp_path):
    p = frame_paths(tmp_path, 42)
    assert p == frame_paths(tmp_path, "000042", split_dir="training")
    assert p.velodyne == tmp_path / "training" / "velodyne" / "000042.bin"
    assert p.label_2 == tmp_path / "training" / "label_2" / "000042.txt"
    assert p.calib == tmp_path / "training" / "calib" / "000042.txt"
    assert frame_paths(tmp_path, 7, split_dir="testing").image_2 == tmp_path / "testing" / "image_2" / "000007.png"
    p.image_2.parent.mkdir(parents=True)
    Image.new("P", (1242, 375)).save(p.image_2)
    assert read_image_size(p.image_2) == (1242, 375)
    p.calib.parent.mkdir(parents=True)
    p.calib.write_text("not a png")
    with raises_at(p.calib, None, "cannot read image header"):
        read_image_size(p.calib)
    with raises_at(tmp_path / "x.png", None, "not found"):
        read_image_size(tmp_path / "x.png")
