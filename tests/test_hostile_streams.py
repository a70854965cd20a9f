"""Hostile stream folders (issue 33): an impossible sensor rate, region or image size in ``stream.json`` is one
``InputError`` naming the file, before any sequence is read; and (issue 47) every command that reads a stream
(``mpchair view --mcap / --rerun``, ``detector stream-eval``) refuses the same files, NaN scan points included."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers_recordings import small_stream

from detector.stream.data import read_stream
from mpchair.core.errors import InputError
from mpchair.kitti import read_velodyne, write_velodyne

GOOD = {"rate_hz": 10.0, "region": {"max_abs_dz": 1.5, "max_distance": 10.0, "half_fov": 0.78},
        "image_size": [640, 480], "sequences": {}}


@pytest.mark.parametrize("edit, message", [
    ({"rate_hz": 0}, "rate_hz: expected a sensor rate in [0.001, 1000] Hz, got 0.0"),
    ({"rate_hz": float("nan")}, "rate_hz: expected a sensor rate"),
    ({"rate_hz": -10}, "rate_hz: expected a sensor rate"),
    ({"rate_hz": 1e300}, "rate_hz: expected a sensor rate"),
    ({"rate_hz": 1e-300}, "rate_hz: expected a sensor rate"),
    ({"region": {"max_abs_dz": 1.5, "max_distance": float("inf"), "half_fov": None}}, "region: expected positive"),
    ({"region": {"max_abs_dz": -1, "max_distance": 10.0, "half_fov": None}}, "region: expected positive"),
    ({"image_size": [0, 480]}, "image_size: expected a positive width and height"),
    ({"rate_hz": "fast"}, "malformed stream file (ValueError"),
    ({"image_size": [640.5, 480]}, "malformed stream file (ValueError: expected a whole number, got 640.5)"),
    ({"sequences": {"../../etc": {}}}, "sequences: expected names of digits (00, 01, ...), got '../../etc'"),
])
def test_impossible_stream_metadata_is_refused(tmp_path, edit, message):
    (tmp_path / "stream.json").write_text(json.dumps({**GOOD, **edit}))
    with pytest.raises(InputError) as err:
        read_stream(tmp_path)
    assert str(err.value).startswith(f"{tmp_path / 'stream.json'}: {message}"), err.value


def test_a_sane_stream_file_gets_past_the_checks(tmp_path):
    """The checks can pass: the good metadata reaches the next check (no sequences)."""
    (tmp_path / "stream.json").write_text(json.dumps(GOOD))
    with pytest.raises(InputError, match="the stream has no sequences"):
        read_stream(tmp_path)


def test_non_utf8_stream_file_is_one_line(tmp_path):
    (tmp_path / "stream.json").write_bytes(b'{"rate_hz": "\xff"}')
    with pytest.raises(InputError, match=r"stream.json:1: not UTF-8 text \(byte 13 is 0xff\)"):
        read_stream(tmp_path)


# --- one check of a stream for every command that reads one (issue 47) ---------------------------------------------

#: Every command that reads a whole stream: ``(program, arguments before the output, output file name)``.
READERS = {
    "view --mcap": ("mpchair", ["view", "{data}", "--mcap"], "out.mcap"),
    "view --rerun": ("mpchair", ["view", "{data}", "--rerun"], "out.rrd"),
    "stream-eval": ("detector", ["stream-eval", "--data", "{data}", "--oracle", "--latency-ms", "0", "--quiet",
                                 "--mcap"], "out.mcap"),
}
#: The picture of one frame of a stream (``mpchair view --out``), which reads that frame's scan alone.
PICTURE = {"view --out": ("mpchair", ["view", "{data}", "--sequence", "00", "--frame", "1", "--out"], "frame.png")}


def _read_with(command: str, data: Path, out_dir: Path, capsys) -> tuple[int, str, Path]:
    """Run ``command`` of :data:`READERS` or :data:`PICTURE` on the stream ``data`` in this process: ``(exit status,
    stderr, output)``."""
    from detector.cli import main as detector_main
    from mpchair.cli import main as mpchair_main

    prog, args, name = {**READERS, **PICTURE}[command]
    out = out_dir / name
    with pytest.raises(SystemExit) as e:
        (mpchair_main if prog == "mpchair" else detector_main)([a.format(data=data) for a in args] + [str(out)])
    return e.value.code, capsys.readouterr().err, out


@pytest.mark.parametrize("command", sorted(READERS))
@pytest.mark.parametrize("rate", [1e300, 0, float("nan"), 1e-300])
def test_every_stream_reader_refuses_the_same_rate(tmp_path, capsys, command, rate):
    """The third audit: ``view --mcap`` accepted rate_hz 1e300, ``view --rerun`` 0, NaN and 1e300 (stream-eval
    refused them); one check now refuses them in all three, naming the file, before any output is opened."""
    pytest.importorskip("rerun" if "rerun" in command else "mcap")
    data = small_stream(tmp_path / "st", rate)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    code, err, _ = _read_with(command, data, out_dir, capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    want = f"error: {data / 'stream.json'}: rate_hz: expected a sensor rate in [0.001, 1000] Hz"
    assert lines[0].startswith(want), err
    assert list(out_dir.iterdir()) == []  # no recording, no temporary


@pytest.mark.parametrize("command", sorted(READERS) + sorted(PICTURE))
def test_every_stream_reader_reads_the_sane_stream_and_refuses_a_nan_point(tmp_path, capsys, command):
    """The same small stream is read whole by each command (so the refusals above are the rate's), and its frame 1
    drawn by ``view --out``; with one NaN in that frame's scan each refuses it with one line naming that scan (NaN
    points passed ``view`` and ``stream-eval`` before), and writes no output."""
    if command in READERS:
        pytest.importorskip("rerun" if "rerun" in command else "mcap")
    data = small_stream(tmp_path / "st")
    code, err, out = _read_with(command, data, tmp_path, capsys)
    assert code == 0 and out.stat().st_size > 0, err
    out.unlink()
    scan = data / "sequences" / "00" / "velodyne" / "000001.bin"
    points = read_velodyne(scan)
    points[7, 1] = np.nan
    write_velodyne(scan, points)
    code, err, out = _read_with(command, data, tmp_path, capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert lines[0] == f"error: {scan}: point 7 has a non-finite y (nan); a scan holds finite x, y, z, reflectance"
    assert not out.exists() and not list(tmp_path.glob(f".{out.name}.*"))


def test_a_nan_point_is_refused_where_a_model_reads_its_frame(tmp_path):
    """stream-eval's model reads each frame with detector's frame loader, which reads the scan with the same check
    (an infinite reflectance too)."""
    from detector.data.kitti_dataset import load_frame

    data = small_stream(tmp_path / "st")
    scan = data / "sequences" / "00" / "velodyne" / "000000.bin"
    args = dict(classes=("Chair",), fov_crop=False, split_dir="00", with_labels=False)  # as ModelRunner.frame
    assert len(load_frame(data / "sequences", "000000", **args).points) > 0
    points = read_velodyne(scan)
    points[0, 3] = np.inf
    write_velodyne(scan, points)
    with pytest.raises(InputError, match=rf"^{scan}: point 0 has a non-finite reflectance \(inf\)"):
        load_frame(data / "sequences", "000000", **args)


@pytest.mark.parametrize("latency", ["inf", "1e300", "nan", "-1"])
def test_a_latency_out_of_range_is_one_line(tmp_path, capsys, latency):
    """``stream-eval --latency-ms inf`` and ``1e300`` ended in an OverflowError traceback (the schedule counts integer
    microseconds); now one line, exit 2."""
    from helpers_detector import detector_cli

    data = small_stream(tmp_path / "st")
    code, _, err = detector_cli(["stream-eval", "--data", data, "--oracle", "--latency-ms", latency, "--quiet"], capsys)
    lines = err.strip().splitlines()
    assert code == 2 and lines == [f"error: --latency-ms must be >= 0 and at most 3.6e+06 (an hour), got "
                                   f"{float(latency)}"], err


@pytest.mark.parametrize("command", sorted(READERS))
def test_a_killed_recordings_temporaries_are_removed_by_the_next_recording(tmp_path, capsys, command):
    """A killed ``view --mcap / --rerun`` (or ``stream-eval --mcap``) left its ``.OUT.<12 hex>.tmp`` (up to 15 MB,
    never removed: the third audit); the next recording of the same file removes it. A user's file that only looks
    like one (another name pattern) stays, byte for byte."""
    pytest.importorskip("rerun" if "rerun" in command else "mcap")
    data = small_stream(tmp_path / "st")
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    name = READERS[command][2]
    dead = out_dir / f".{name}.0123456789ab.tmp"  # a killed writer's: nobody holds its lock
    dead.write_bytes(b"x" * 100_000)
    mine = out_dir / f".{name}.draft.tmp"
    mine.write_text("mine")
    code, err, out = _read_with(command, data, out_dir, capsys)
    assert code == 0 and out.stat().st_size > 0, err
    assert sorted(p.name for p in out_dir.iterdir()) == sorted([name, mine.name]) and mine.read_text() == "mine"


@pytest.mark.parametrize("command", sorted(READERS))
def test_every_stream_reader_refuses_a_stream_file_nested_deep_with_one_line(tmp_path, capsys, command):
    """The third audit: ``stream.json`` nested 100,000 levels deep ended each reader in a RecursionError traceback.
    Through the command line now: one line naming the file, exit 2, no recording and no temporary."""
    pytest.importorskip("rerun" if "rerun" in command else "mcap")
    data = small_stream(tmp_path / "st")
    (data / "stream.json").write_text('{"rate_hz": 10, "sequences": ' + "[" * 100_000 + "]" * 100_000 + "}")
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    code, err, _ = _read_with(command, data, out_dir, capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert lines[0] == f"error: {data / 'stream.json'}: nested deeper than 64 levels", err
    assert list(out_dir.iterdir()) == []

