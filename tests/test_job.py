"""The job skeleton ``generate`` and ``stream`` share (mpchair/dataset/job.py): the recorded command line, the
settings-file check, stale temp removal and the worker pool's errors."""

from __future__ import annotations

import functools
import json
import os
from pathlib import Path

import pytest

from mpchair.core.errors import InputError, RunError
from mpchair.dataset import job

KIND = job.JobKind(command="generate", folder="dataset", settings_file=".generate.json")


def test_command_line_writes_the_flags_in_order_and_leaves_out_what_is_unset() -> None:
    line = job.command_line(KIND, Path("/data/mp3d/houses"), ("A", "B"), [
        ("--frames", 3), ("--height", 1.25), ("--rate", 2.0), ("--category", ("chair", "table")),
        ("--val-house", ()), ("--keep-empty", True), ("--no-look-around", False), ("--duration", None),
        ("--split-mode", "house")])  # fmt: skip
    assert line == ("mpchair", "generate", "--root", "houses", "--house", "A", "--house", "B", "--frames", "3",
                    "--height", "1.25", "--rate", "2.0", "--category", "chair", "--category", "table", "--keep-empty",
                    "--split-mode", "house")
    # a float reads back to the same number
    assert float(job.command_line(KIND, Path("r"), ("A",), [("--x", 0.1 + 0.2)])[-1]) == 0.1 + 0.2


def test_settings_are_written_into_a_new_folder_and_checked_on_a_re_run(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    out.mkdir()
    (out / ".generate-0-of-1.lock").touch()  # ours: the folder counts as new
    (out / "..generate.json.0123456789ab.tmp").write_text("{")  # a killed settings write
    ours = lambda name: name.endswith(".lock")  # noqa: E731
    job.check_settings(KIND, out, {"seed": 1, "frames": 2}, alone=True, replace=False, ours=ours)
    assert json.loads((out / ".generate.json").read_text()) == {"frames": 2, "seed": 1}
    assert not list(out.glob("*.tmp"))
    job.check_settings(KIND, out, {"frames": 2, "seed": 1}, alone=True, replace=False, ours=lambda n: False)
    with pytest.raises(InputError, match=r"holds a dataset made with other settings \(frames, seed differ\)"):
        job.check_settings(KIND, out, {"seed": 2, "frames": 3}, alone=True, replace=False, ours=lambda n: False)
    job.check_settings(KIND, out, {"seed": 2}, alone=True, replace=True, ours=lambda n: False)
    assert json.loads((out / ".generate.json").read_text()) == {"seed": 2}


def test_a_corrupt_settings_file_and_a_foreign_folder_are_input_errors(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    out.mkdir()
    (out / ".generate.json").write_text("[1, 2")
    with pytest.raises(InputError, match="the file is not a settings object"):
        job.check_settings(KIND, out, {"seed": 1}, alone=True, replace=False, ours=lambda n: False)
    other = tmp_path / "photos"
    other.mkdir()
    (other / "cat.jpg").write_bytes(b"\xff")
    with pytest.raises(InputError, match=r"photos: exists and is not an mpchair dataset folder \(no \.generate\.json"):
        job.check_settings(KIND, other, {"seed": 1}, alone=True, replace=False, ours=lambda n: False)
    assert sorted(p.name for p in other.iterdir()) == ["cat.jpg"]


def test_remove_temps_removes_only_the_owned_temps(tmp_path: Path) -> None:
    d = tmp_path / "velodyne"
    d.mkdir()
    for name in (".000001.bin.aa.tmp", ".000002.bin.bb.tmp", "000001.bin", "notes.tmp"):
        (d / name).write_text("x")
    job.remove_temps([d, tmp_path / "missing"], owned=lambda name: name[1:7] == "000001")
    assert sorted(p.name for p in d.iterdir()) == [".000002.bin.bb.tmp", "000001.bin", "notes.tmp"]
    job.remove_temps([d])
    assert sorted(p.name for p in d.iterdir()) == ["000001.bin", "notes.tmp"]


def _square(n: int) -> int:
    if n == 3:
        raise ValueError("three")
    return n * n


def _die(n: int) -> int:
    os._exit(7)


def test_make_tasks_runs_every_task_and_turns_a_worker_failure_into_a_run_error(tmp_path: Path) -> None:
    got = []
    seconds = job.make_tasks(functools.partial(pow, 2), [1, 2, 4], 5, workers=1, out=tmp_path, kind=KIND,
                             progress=False, is_done=lambda t: False, account=lambda r: got.append(r) or {})
    assert got == [2, 4, 16] and seconds >= 0
    with pytest.raises(RunError, match=r"a worker process failed: ValueError: three; stopped the other workers; "
                                       r"the frames written so far are kept"):
        job.make_tasks(_square, [1, 2, 3, 4, 5], 5, workers=2, out=tmp_path, kind=KIND, progress=False,
                       is_done=lambda t: False)
    with pytest.raises(ValueError, match="three"):  # in one process: the error itself
        job.make_tasks(_square, [3], 1, workers=2, out=tmp_path, kind=KIND, progress=False, is_done=lambda t: False)
    with pytest.raises(RunError, match=r"worker process \d+ exited with status 7; stopped the other workers"):
        job.make_tasks(_die, [1, 2], 2, workers=2, out=tmp_path, kind=KIND, progress=False, is_done=lambda t: False)
