"""KITTI-odometry sequence files: exact microsecond times through the text round trip, poses, and the clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from mpchair.core.errors import InputError
from mpchair.geometry import yaw_matrix
from mpchair.kitti import format_times, read_poses, read_times, write_poses, write_times


def test_times_round_trip_exactly(tmp_path):
    t = np.round(np.arange(500) * (1e6 / 30.0)).astype(np.int64)  # 30 Hz: periods of 33333 / 33334 us
    write_times(tmp_path / "times.txt", t)
    assert np.array_equal(read_times(tmp_path / "times.txt"), t)
    assert format_times(np.array([0, 1, 33_333, 12_000_000])) == "0.000000\n0.000001\n0.033333\n12.000000\n"
    (tmp_path / "short.txt").write_text("0\n0.5\n1.25\n")
    assert np.array_equal(read_times(tmp_path / "short.txt"), [0, 500_000, 1_250_000])
    (tmp_path / "kitti.txt").write_text("0.000000e+00\n1.036160e-01\n2.072319e-01\n1.234567e+02\n")  # KITTI's
    assert np.array_equal(read_times(tmp_path / "kitti.txt"), [0, 103_616, 207_232, 123_456_700])


def test_poses_round_trip(tmp_path):
    poses = yaw_matrix(np.linspace(-3, 3, 7))
    poses[:, :3, 3] = np.arange(21).reshape(7, 3) * 0.37
    write_poses(tmp_path / "poses.txt", poses)
    assert np.allclose(read_poses(tmp_path / "poses.txt"), poses, rtol=1e-9, atol=1e-12)
    assert len((tmp_path / "poses.txt").read_text().splitlines()[0].split()) == 12


@pytest.mark.parametrize("text, line, message", [
    ("0.0\n0.5\n0.5\n", 3, "must increase"),
    ("0.0\n0.0000001\n", 2, "must increase"),
    ("0.0\n-0.5\n", 2, "expected a time in seconds"),
    ("0.0\nnan\n", 2, "expected a time in seconds"),
    ("0.0\nabc\n", 2, "expected a time in seconds"),
    ("0.0\n1e300\n", 2, "expected a time in seconds"),
])
def test_bad_times_name_the_line(tmp_path, text, line, message):
    (tmp_path / "t.txt").write_text(text)
    with pytest.raises(InputError, match=f"t.txt:{line}: .*{message}"):
        read_times(tmp_path / "t.txt")


IDENTITY = "1 0 0 0 0 1 0 0 0 0 1 0\n"


def test_bad_poses_name_the_line(tmp_path):
    (tmp_path / "p.txt").write_text(IDENTITY + " ".join(["1"] * 11) + "\n")
    with pytest.raises(InputError, match="p.txt:2: expected 12 finite numbers"):
        read_poses(tmp_path / "p.txt")
    # a scale, a shear, a mirror
    for bad in ("2 0 0 0 0 1 0 0 0 0 1 0", "1 0.5 0 0 0 1 0 0 0 0 1 0", "-1 0 0 0 0 1 0 0 0 0 1 0"):
        (tmp_path / "p.txt").write_text(IDENTITY + IDENTITY + bad + "\n")
        with pytest.raises(InputError, match="p.txt:3: not a rigid pose"):
            read_poses(tmp_path / "p.txt")
    with pytest.raises(InputError, match="not found"):
        read_poses(tmp_path / "none.txt")


@pytest.mark.parametrize("reader", [read_times, read_poses])
def test_non_utf8_sequence_files_name_the_line(tmp_path, reader):
    (tmp_path / "f.txt").write_bytes(b"0.0\n\xff\xfe\n")
    with pytest.raises(InputError, match=r"f.txt:2: not UTF-8 text \(byte 4 is 0xff\)"):
        reader(tmp_path / "f.txt")
