"""Numbers and environment variables a user controls are checked before any work, with one ``error:`` line and exit
2 (mpchair.core.limits): seeds beyond 32 bits, thread and worker counts beyond the machine (``--threads 100000``
used to segfault), non-finite or non-positive rates and durations, and ``DETECTOR_GEMM`` / ``WORLD_SIZE`` /
``RANK`` / ``LOCAL_RANK`` / ``MPLBACKEND`` values no command can use (each used to end in a traceback)."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import pytest
from helpers_detector import detector_cli

from mpchair.cli import main as mpchair_main
from mpchair.core.limits import MAX_SEED, max_parallel
from reproduction.cli import main as reproduce_main


def _mpchair(args: list, capsys) -> tuple[int, str]:
    with pytest.raises(SystemExit) as e:
        mpchair_main([str(a) for a in args])
    return e.value.code, capsys.readouterr().err


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    return lines[0]


@pytest.mark.parametrize("args, needle", [
    (["eval", "--config", "c.yaml", "--data", "d", "--threads", "100000"], "--threads"),
    (["stream-eval", "--config", "c.yaml", "--data", "d", "--threads", "0"], "--threads"),
    (["stream-eval", "--config", "c.yaml", "--data", "d", "--threads", "100000"], "--threads"),
    (["stream-eval", "--config", "c.yaml", "--data", "d", "--repeats", str(10**20)], "--repeats"),
    (["stream-eval", "--config", "c.yaml", "--data", "d", "--warmup", "100000"], "--warmup"),
    (["bench", "--config", "c.yaml", "--threads", "100000"], "--threads"),
    (["train", "--config", "c.yaml", "--data", "d", "--out", "o", "--threads", "100000"], "--threads"),
    (["bench", "--config", "c.yaml", "--rate", "nan"], "--rate"),
    (["bench", "--config", "c.yaml", "--rate", "inf"], "--rate"),
    (["bench", "--config", "c.yaml", "--rate", "1e-300"], "--rate"),
    (["bench", "--config", "c.yaml", "--rate", "10", "--duration", "nan"], "--duration"),
    (["bench", "--config", "c.yaml", "--rate", "10", "--duration", "-1"], "--duration"),
    (["export", "--config", "c.yaml", "--format", "onnx", "--out", "o", "--seed", str(2**64)], "--seed"),
])
def test_detector_numbers_out_of_range_are_one_line(args, needle, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, _, err = detector_cli(args, capsys)
    assert code == 2 and needle in _one_line(err)
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("args", [
    ["generate", "--root", "r", "--house", "h", "--frames", "1", "--out", "o", "--workers", str(max_parallel() + 1)],
    ["generate", "--root", "r", "--house", "h", "--frames", "1", "--out", "o", "--seed", str(MAX_SEED + 1)],
    ["stream", "--root", "r", "--house", "h", "--out", "o", "--workers", "100000"],
    ["synth", "--out", "o", "--seed", "99999999999999999999999"],
])
def test_mpchair_numbers_out_of_range_are_one_line(args, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, err = _mpchair(args, capsys)
    assert code == 2 and ("--workers" in _one_line(err) or "--seed" in err)
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("option, value, needle", [
    ("--rate", "5000", "--rate must be a positive sensor rate of at most 1000 Hz (what every stream reader accepts), "
                       "got 5000.0"),  # every reader refused the stream it wrote
    ("--rate", "1e300", "--rate must be a positive sensor rate"),  # "Maximum allowed size exceeded" before
    ("--rate", "nan", "--rate must be a positive sensor rate"),
    ("--speed", "nan", "--speed must be 0 (a robot that stays put) or a finite number >= 0.01 m/s, got nan"),
    ("--speed", "1e-9", "--speed must be 0"),  # a drive simulated for 4 x path / speed: forever
    ("--accel", "inf", "--accel must be a finite number > 0 m/s^2, got inf"),
    ("--turn-rate", "-1", "--turn-rate must be a finite number >= 0 rad/s, got -1.0"),
    ("--duration", "1e300", "--duration must be from 0 to 3600 seconds per episode, got 1e+300"),  # memory grew
    ("--episodes", "100000000000", "--episodes must be from 1 to 10000 per house"),  # planned forever
])
def test_stream_motion_numbers_out_of_range_are_one_line(option, value, needle, capsys, tmp_path, monkeypatch):
    """The third audit's families re-run on ``mpchair stream`` (issue 47): each of these was accepted (a stream at
    5000 Hz that every reader refuses, a NaN speed written into stream.json, an infinite acceleration) or planned
    without end; each is now one line naming the option, before any file or house is read."""
    monkeypatch.chdir(tmp_path)
    args = ["stream", "--root", "r", "--house", "h", "--episodes", "1", "--out", "o", "--speed", "0", "--duration",
            "1", option, value]  # the last of a repeated option counts
    code, err = _mpchair(args, capsys)
    assert code == 2 and _one_line(err).startswith(f"error: {needle}"), err
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("args, needle", [
    (["--size", "100000", "100000"], "Invalid value for --size: pictures need from 64 x 64 to 8192 x 8192 pixels"),
    (["--extent", "nan", "1", "2", "3"], "Invalid value for --extent: expected finite XMIN < XMAX and YMIN < YMAX"),
    (["--extent", "5", "1", "2", "3"], "Invalid value for --extent"),
])
def test_view_picture_sizes_and_windows_out_of_range_are_one_line(args, needle, capsys, tmp_path, monkeypatch):
    """The re-run of the third audit's families: ``--size 100000 100000`` ended in ``MemoryError: std::bad_alloc``
    (a traceback), ``--extent nan ...`` drew an empty picture and exited 0."""
    monkeypatch.chdir(tmp_path)
    code, err = _mpchair(["view", "d", "--frame", "0", "--out", "x.png", *args], capsys)
    assert code == 2 and _one_line(err).startswith(f"error: {needle}"), err
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("env, needle", [
    ({"DETECTOR_GEMM": "bogus"}, "DETECTOR_GEMM='bogus'"),
    ({"WORLD_SIZE": "abc"}, "WORLD_SIZE='abc' is not a whole number"),
    ({"RANK": "abc"}, "RANK='abc'"),
    ({"WORLD_SIZE": "0"}, "WORLD_SIZE=0 must be >= 1"),
    ({"WORLD_SIZE": "1", "RANK": "5"}, "RANK=5 must be below WORLD_SIZE=1"),
    ({"WORLD_SIZE": "2", "RANK": "0"}, "start distributed runs with torchrun"),
    ({"MPLBACKEND": "bogus"}, "MPLBACKEND='bogus' is not a matplotlib backend"),
])
def test_environment_variables_are_checked_with_one_line(env, needle, capsys, monkeypatch):
    for k in ("DETECTOR_GEMM", "WORLD_SIZE", "RANK", "LOCAL_RANK", "MPLBACKEND", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(k, raising=False)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    code, _, err = detector_cli(["train", "--config", "c.yaml", "--data", "d", "--out", "o"], capsys)
    assert code == 2 and needle in _one_line(err)
    code, err = _mpchair(["houses", "--root", "r"], capsys)
    assert code == 2 and needle in _one_line(err)


def test_reproduce_bounds_threads_workers_and_seed(capsys, tmp_path):
    for flag, value in (("--threads", "100000"), ("--workers", "0"), ("--seed", str(2**70))):
        assert reproduce_main(["--scale", "small", "--out", str(tmp_path / "w"), "--dry-run", flag, value]) == 2
        assert "--threads and --workers take 1 to" in _one_line(capsys.readouterr().err)
    assert not (tmp_path / "w").exists()


# --- special files, nesting and edited records -----------------------------------------------------------------------


def _deep(n: int) -> str:
    return '{"sequences": ' + "[" * n + "]" * n + "}"


def test_special_files_and_deep_nesting_are_refused_not_read(tmp_path):
    from detector.stream.data import read_stream
    from mpchair.core.errors import InputError
    from mpchair.core.text import load_json, read_regular
    from mpchair.recording.sources import read_stream_meta

    fifo = tmp_path / "fifo.json"
    os.mkfifo(fifo)  # reading it would block forever
    with pytest.raises(InputError, match=rf"^{fifo}: x is a FIFO, not a regular file"):
        read_regular(fifo, "x")
    (tmp_path / "dir.json").mkdir()
    with pytest.raises(InputError, match="is a folder, not a regular file"):
        load_json(tmp_path / "dir.json", "x")
    (tmp_path / "zero").symlink_to("/dev/zero")  # reading it would grow without end
    with pytest.raises(InputError, match="is a character device"):
        read_regular(tmp_path / "zero", "x")
    for n in (100, 100_000):
        stream = tmp_path / f"s{n}"
        stream.mkdir()
        (stream / "stream.json").write_text(_deep(n))
        with pytest.raises(InputError, match=rf"^{stream / 'stream.json'}: nested deeper than 64 levels"):
            read_stream_meta(stream)
        with pytest.raises(InputError, match="nested deeper than 64 levels"):
            read_stream(stream)


def _work_with_run(tmp_path: Path, config: str, metrics: str) -> Path:
    run = tmp_path / "w" / "runs" / "dense"
    run.mkdir(parents=True)
    (run / "config.yaml").write_text(config)
    (run / "metrics.jsonl").write_text(metrics)
    return tmp_path / "w"


def test_status_on_odd_work_folders_is_one_line_or_skips_odd_lines(tmp_path, capsys):
    from helpers_detector import write_run_config

    # a whole config.yaml as detector train writes it (its readers check it as a config)
    good = write_run_config(tmp_path / "cfg", train=dict(epochs=2, batch_size=2, samples_per_epoch=4)).read_text()
    odd_lines = '[1]\n{"kind": "step"}\n{"kind": "step", "step": "x", "time_s": 1}\n' + _deep(5000) + "\n"
    work = _work_with_run(tmp_path / "a", good, odd_lines + '{"kind": "step", "step": 1, "epoch": 0, "time_s": 0.5}\n')
    assert reproduce_main(["--status", "--out", str(work)]) == 0
    assert "dense: step 1 / 4" in capsys.readouterr().out

    step = '{"kind": "step", "step": 1, "epoch": 0, "time_s": 0.5}\n'
    for name, config in (("zero", good.replace("batch_size: 2", "batch_size: 0")),
                         ("yaml", "train: [1, 2\n"), ("fifo", good), ("dir", good), ("devzero", good)):
        work = _work_with_run(tmp_path / name, config, step)
        if name == "fifo":
            (work / "runs/dense/metrics.jsonl").unlink()
            os.mkfifo(work / "runs/dense/metrics.jsonl")
        if name == "devzero":  # read whole, it grew ~1 GB/s (the third audit)
            (work / "runs/dense/metrics.jsonl").unlink()
            (work / "runs/dense/metrics.jsonl").symlink_to("/dev/zero")
        if name == "dir":
            (work / "runs/dense/metrics.jsonl").unlink()
            (work / "runs/dense/metrics.jsonl").mkdir()
        assert reproduce_main(["--status", "--out", str(work)]) == 2, name
        line = _one_line(capsys.readouterr().err)
        assert str(work / "runs" / "dense") in line, (name, line)


def _record(tmp_path: Path, **meta) -> Path:
    import json

    rec = tmp_path / "rec"
    (rec / "results").mkdir(parents=True)
    (rec / "results/a.json").write_text("{}")
    from reproduction.scales import SCALES

    sizes = dataclasses.asdict(SCALES["small"])
    base = {"scale": "small", "notes": [], "dataset_sha256": None, "files": ["results/a.json"]}
    meta = {**base, **meta, "scale_sizes": {**sizes, **meta.get("scale_sizes", {})}}
    (rec / "record.json").write_text(json.dumps(meta))
    return rec


@pytest.mark.parametrize("meta, needle", [
    ({"files": [""]}, "files: expected relative paths"),
    ({"files": [123]}, "files: expected relative paths"),
    ({"scale_sizes": {"gigantic": 1}}, "scale_sizes: unknown key 'gigantic'"),
    ({"notes": 5}, "notes: expected a list"),
    ({"notes": "hello"}, "notes: expected a list"),
    ({"scale": "gigantic"}, "scale: expected one of"),
    ({"scale_sizes": {"precision": "fp7"}}, "scale_sizes.precision"),
    ({"scale_sizes": {"epochs": -3}}, "scale_sizes.epochs"),
    ({"scale_sizes": {"houses": 10**12}}, "scale_sizes.houses"),
    ({"scale_sizes": {"budget_seconds": float("nan")}}, "scale_sizes.budget_seconds"),
    ({"files": ["results/a.json", "dataset/manifest.json"]}, "dataset_sha256: missing"),
    ({"dataset_sha256": "abc"}, "dataset_sha256: expected 64 hex digits"),
])
def test_an_edited_record_is_refused_naming_the_field(meta, needle, tmp_path):
    from reproduction.record import RecordError, read_record

    with pytest.raises(RecordError, match=needle):
        read_record(_record(tmp_path, **meta))


def test_a_record_is_restored_only_from_regular_files_inside_it(tmp_path):
    from reproduction.record import RecordError, restore_record, save_record
    from reproduction.scales import SCALES

    rec = _record(tmp_path)
    (rec / "results/a.json").unlink()
    (rec / "results/a.json").symlink_to("/etc/passwd")
    with pytest.raises(RecordError, match="a symbolic link"):
        restore_record(rec, tmp_path / "out", with_dataset=False)
    assert not (tmp_path / "out" / "results/a.json").exists()

    work = tmp_path / "w"  # a link in a work folder is not saved into the next record either
    (work / "results").mkdir(parents=True)
    (work / "results/evil.json").symlink_to("/etc/passwd")
    (work / "results/ok.json").write_text("{}")
    save_record(work, tmp_path / "rec2", "small", SCALES["small"], [])
    assert sorted(p.name for p in (tmp_path / "rec2/results").iterdir()) == ["ok.json"]


def test_a_record_with_a_link_after_a_regular_file_restores_nothing(tmp_path, capsys):
    """tests/hostile_audit.py's re-run (issue 47): ``results/a.json`` was copied into the work folder before
    ``results/evil.json -> /etc/passwd`` was met and refused, so the refused run left a work folder with part of the
    record. Every file is checked before the first is copied: one line, exit 2, no work folder."""
    import json

    from reproduction.scales import SCALES

    rec = tmp_path / "rec"
    (rec / "results").mkdir(parents=True)
    (rec / "results/a.json").write_text("{}")
    (rec / "results/evil.json").symlink_to("/etc/passwd")
    (rec / "record.json").write_text(json.dumps({
        "scale": "small", "scale_sizes": dataclasses.asdict(SCALES["small"]), "notes": [], "dataset_sha256": None,
        "files": ["results/a.json", "results/evil.json"]}))
    code = reproduce_main(["--from-record", str(rec), "--steps", "report", "--out", str(tmp_path / "w")])
    line = _one_line(capsys.readouterr().err)
    assert code == 2 and "results/evil.json: a symbolic link" in line, line
    assert sorted(os.listdir(tmp_path)) == ["rec"]


@pytest.mark.parametrize("edit, needle", [
    (("beams: 16", "beams: 100000000"), "one scan needs at least"),  # 1.8e11 rays; 100,000 beams used to hit the OOM
    (("columns: 1800", "columns: 1e9"), "columns"),
    (("beams: 16", "beams: 0"), "beams and columns must be whole numbers >= 1"),
    (("width: 1024", "width: 10000000"), "one scan needs at least"),
    (("height: 1024", "height: 10000000"), "one scan needs at least"),
])
def test_a_sensor_too_large_for_the_machine_is_refused_before_allocating(edit, needle, tmp_path):
    from mpchair.core.errors import InputError
    from mpchair.scan.sensors import load_sensor

    text = (Path(__file__).resolve().parents[1] / "mpchair/scan/profiles/lidar16.yaml").read_text()
    assert edit[0] in text
    path = tmp_path / "s.yaml"
    path.write_text(text.replace(*edit))
    with pytest.raises(InputError, match=needle) as e:
        load_sensor(path)
    assert str(e.value).startswith(str(path)) and "\n" not in str(e.value)


def test_a_pinhole_row_step_of_zero_is_refused(tmp_path):
    from mpchair.core.errors import InputError
    from mpchair.scan.sensors import load_sensor

    text = (Path(__file__).resolve().parents[1] / "mpchair/scan/profiles/mp3d-depth90.yaml").read_text()
    path = tmp_path / "s.yaml"
    path.write_text(text.replace("row_step: 10", "row_step: 0"))
    assert "row_step: 0" in path.read_text()
    with pytest.raises(InputError, match="row_step and flat_step must be whole numbers >= 1"):
        load_sensor(path)
    assert load_sensor("mp3d-depth90").pinhole.row_step == 10  # the shipped sensors pass


def test_temporaries_of_a_killed_writer_are_removed_and_a_live_writers_kept(tmp_path):
    import fcntl

    from mpchair.core.atomic import atomic_path, remove_dead_temps

    out = tmp_path / "x.rrd"
    dead = tmp_path / ".x.rrd.0123456789ab.tmp"  # a killed `view --rerun`'s: nobody holds it
    dead.write_bytes(b"x" * 1000)
    mine = tmp_path / ".x.rrd.notes.tmp"  # not a temporary's name
    mine.write_text("mine")
    with atomic_path(out) as live:  # a live writer holds its temporary
        Path(live).write_bytes(b"y")
        assert remove_dead_temps(out) == [dead]
        assert Path(live).exists() and mine.exists()
        fd = os.open(live, os.O_RDONLY)
        try:
            with pytest.raises(BlockingIOError):
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        finally:
            os.close(fd)
    assert out.read_bytes() == b"y" and sorted(p.name for p in tmp_path.iterdir()) == [".x.rrd.notes.tmp", "x.rrd"]


def test_a_lone_distributed_rank_gives_up_with_one_line(tmp_path):
    """WORLD_SIZE=2 RANK=0 with nobody else: an error after the join timeout, not a wait of the job's 6 hours."""
    import socket
    import subprocess
    import sys

    from helpers_detector import make_tiny_dataset, write_test_config

    data = make_tiny_dataset(tmp_path / "ds", n_frames=2, seed=0)
    cfg = write_test_config(tmp_path / "cfg.yaml", train=dict(batch_size=1, epochs=1))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(root), "WORLD_SIZE": "2", "RANK": "0", "LOCAL_RANK": "0",
           "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port), "DETECTOR_JOIN_TIMEOUT_S": "2"}
    env.pop("TORCHELASTIC_USE_AGENT_STORE", None)
    res = subprocess.run([sys.executable, "-m", "detector", "train", "--config", str(cfg), "--data", str(data),
                          "--out", str(tmp_path / "run"), "--threads", "1", "--no-progress"], env=env,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 2
    assert "rank 0 of 2: the other ranks did not join" in _one_line(res.stderr)


def _small_sizes() -> dict:
    from reproduction.scales import SCALES

    return dataclasses.asdict(SCALES["small"])


@pytest.mark.parametrize("content", [b'{"a": ', b"\xff\xfe{}", b"[" * 100_000])
def test_from_record_with_a_malformed_results_json_is_one_line(content, tmp_path, capsys):
    """The record's report inputs are read like every work-folder file: malformed, non-UTF-8 or deeply nested JSON
    is one line naming the file."""
    import json

    rec = tmp_path / "rec"
    (rec / "results").mkdir(parents=True)
    (rec / "results/eval_dense").mkdir()
    (rec / "results/eval_dense/metrics.json").write_bytes(content)
    (rec / "record.json").write_text(json.dumps({"scale": "small", "scale_sizes": _small_sizes(), "notes": [],
                                                 "dataset_sha256": None, "files": ["results/eval_dense/metrics.json"]}))
    code = reproduce_main(["--from-record", str(rec), "--steps", "report", "--out", str(tmp_path / "w")])
    line = _one_line(capsys.readouterr().err)
    assert code == 2 and "eval_dense/metrics.json" in line, line


@pytest.mark.parametrize("text", ["[" * 100_000 + "]" * 100_000, '{"files": ' + "[" * 100_000])
def test_from_record_with_a_record_json_nested_deep_is_one_line(text, tmp_path, capsys):
    """``--from-record`` on a record whose record.json nests 100,000 deep (the third audit: a traceback): one line
    naming the file, exit 2, and no work folder."""
    rec = tmp_path / "rec"
    rec.mkdir()
    (rec / "record.json").write_text(text)
    code = reproduce_main(["--from-record", str(rec), "--steps", "report", "--out", str(tmp_path / "w")])
    line = _one_line(capsys.readouterr().err)
    assert code == 2 and str(rec / "record.json") in line and "nested deeper than" in line, line
    assert sorted(os.listdir(tmp_path)) == ["rec"]


def test_a_checkpoint_of_another_format_says_so(tmp_path):
    import torch

    from detector.checkpoint import load_checkpoint
    from mpchair.core.errors import InputError

    path = tmp_path / "x.pt"
    torch.save({"format": 999, "model": {}}, path)
    with pytest.raises(InputError, match=rf"^{path}: checkpoint format 999, but this version reads format 1 only"):
        load_checkpoint(path)
    torch.save({"format": 999}, path)  # another format's keys are its own: the format is what is refused
    with pytest.raises(InputError, match=rf"^{path}: checkpoint format 999, but this version reads format 1 only"):
        load_checkpoint(path)
    torch.save({"weights": {}}, path)
    with pytest.raises(InputError, match="missing format/model keys"):
        load_checkpoint(path)


@pytest.mark.parametrize("content, needle", [(b'{"a": ', "results/b.json"), (b"\xff\xfe{}", "results/b.json"),
                                             (b"[" * 100_000, "nested deeper than")])
def test_a_record_with_a_malformed_json_restores_nothing(tmp_path, capsys, content, needle):
    """tests/hostile_audit.py's full re-run (2026-12-07): a malformed, non-UTF-8 or deeply nested results JSON was
    refused by the report step, after the restore had filled the work folder. Every JSON file of the record is parsed
    before the first is copied: one line naming it, exit 2, no work folder."""
    import json

    from reproduction.scales import SCALES

    rec = tmp_path / "rec"
    (rec / "results").mkdir(parents=True)
    (rec / "results/a.json").write_text("{}")
    (rec / "results/b.json").write_bytes(content)
    (rec / "record.json").write_text(json.dumps({
        "scale": "small", "scale_sizes": dataclasses.asdict(SCALES["small"]), "notes": [], "dataset_sha256": None,
        "files": ["results/a.json", "results/b.json"]}))
    code = reproduce_main(["--from-record", str(rec), "--steps", "report", "--out", str(tmp_path / "w")])
    line = _one_line(capsys.readouterr().err)
    assert code == 2 and needle in line, line
    assert sorted(os.listdir(tmp_path)) == ["rec"]
