"""Rerun recordings on a full disk (issue 33, item 1): ``mpchair view DIR --rerun OUT.rrd`` of a dataset or a stream
on a disk that fills up — or is full from the start — ends within a bounded time with one ``error: OUT.rrd: No space
left on device`` line and exit 2, leaving neither the recording nor a temporary file (it used to hang forever on a
dataset and end in a traceback on a stream). Needs the right to mount a tmpfs (CI runs as root)."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest
from helpers_faults import mounted_tmpfs

from mpchair.synth import plan_houses, synthesize_house, write_house

pytest.importorskip("rerun")

ENV = {**os.environ, "MPLBACKEND": "Agg"}


def _cli(*args, timeout: float = 120) -> tuple[subprocess.CompletedProcess, float]:
    t0 = time.monotonic()
    res = subprocess.run([sys.executable, "-m", "mpchair.cli", *map(str, args)], capture_output=True, text=True,
                         env=ENV, timeout=timeout)
    return res, time.monotonic() - t0


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A small dataset (30 frames) and a 2-second stream of one synthetic house."""
    root = tmp_path_factory.mktemp("rec")
    hid, hs, lv = plan_houses(1, 11)[0]
    write_house(root / "houses", synthesize_house(hs, hid, levels=lv))
    res, _ = _cli("generate", "--root", root / "houses", "--house", hid, "--frames", 30, "--out", root / "ds",
                  "--quiet")
    assert res.returncode == 0, res.stderr
    res, _ = _cli("stream", "--root", root / "houses", "--house", hid, "--episodes", 1, "--duration", 2, "--out",
                  root / "st")
    assert res.returncode == 0, res.stderr
    return root


@pytest.fixture
def tiny_disk(tmp_path):
    with mounted_tmpfs(tmp_path / "disk", "256k") as disk:
        yield disk


@pytest.mark.parametrize("what", ["ds", "st"])
@pytest.mark.parametrize("full_from_the_start", [False, True])
def test_a_full_disk_under_a_recording_is_one_line_exit_2_and_no_file(inputs, tiny_disk, what, full_from_the_start):
    if full_from_the_start:
        st = os.statvfs(tiny_disk)
        (tiny_disk / "filler").write_bytes(b"\0" * (st.f_bavail * st.f_frsize))
    out = tiny_disk / "x.rrd"
    res, seconds = _cli("view", inputs / what, "--rerun", out)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {out}: ") and "No space left on device" in lines[0], lines
    assert sorted(p.name for p in tiny_disk.iterdir()) == (["filler"] if full_from_the_start else [])
    assert seconds < 90  # bounded by the flush timeout, not a hang


def test_the_same_recording_is_written_where_there_is_room(inputs, tmp_path):
    """The checks above can pass only because of the disk: with room, the same commands write the recording."""
    for what in ("ds", "st"):
        out = tmp_path / f"{what}.rrd"
        res, _ = _cli("view", inputs / what, "--rerun", out)
        assert res.returncode == 0, res.stderr
        assert out.stat().st_size > 256 << 10  # larger than the tiny disk


def test_a_stream_on_a_full_disk_names_the_file_and_resumes(inputs, tiny_disk):
    """``mpchair stream`` onto a full disk: one line naming the file and how to resume, exit 2; with room, the same
    command finishes the stream."""
    hid = next((inputs / "houses").rglob("*.house")).stem
    cmd = ("stream", "--root", inputs / "houses", "--house", hid, "--episodes", 1, "--duration", 2, "--out",
           tiny_disk / "st", "--quiet")
    st = os.statvfs(tiny_disk)
    (tiny_disk / "filler").write_bytes(b"\0" * (st.f_bavail * st.f_frsize - (16 << 10)))
    res, _ = _cli(*cmd)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1, res.stderr
    assert lines[0].startswith(f"error: {tiny_disk / 'st'}/") and "No space left on device" in lines[0]
    assert "run the same command again to resume" in lines[0]
    (tiny_disk / "filler").unlink()
    subprocess.run(["mount", "-o", "remount,size=8m", str(tiny_disk)], check=True)
    res, _ = _cli(*cmd)
    assert res.returncode == 0, res.stderr
    assert (tiny_disk / "st" / "stream.json").is_file()


def test_bad_input_inside_a_recording_leaves_the_process_exit_status_alone(inputs, tmp_path):
    """Only a failed write abandons rerun-sdk's stream (and ends the process with status 2): a library caller that
    catches an InputError raised while recording (a broken poses.txt) exits 0, with no file written."""
    import shutil

    stream = tmp_path / "st"
    shutil.copytree(inputs / "st", stream)
    (stream / "sequences" / "00" / "poses.txt").write_text("garbage\n")
    code = ("from mpchair.recording.rerun import log_stream\nfrom mpchair.core.errors import InputError\n"
            f"try:\n    log_stream({str(stream)!r}, {str(tmp_path / 'x.rrd')!r})\n"
            "except InputError as e:\n    print('refused:', e)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith("refused: ") and "poses.txt:1: expected 12 finite numbers" in res.stdout
    assert not (tmp_path / "x.rrd").exists() and not list(tmp_path.glob(".x.rrd.*"))
