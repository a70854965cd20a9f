"""Numbers and environment variables a user controls are checked before any work, with one ``error:`` line and exit
2 (mpchair.core.limits): seeds beyond 32 bits, thread and worker counts beyond the machine (``--threads 100000``
used to segfault), non-finite or non-positive rates and durations, and ``DETECTOR_GEMM`` / ``WORLD_SIZE`` /
``RANK`` / ``LOCAL_RANK`` / ``MPLBACKEND`` values no command can use (each used to end in a traceback)."""

from __future__ import annotations

import os

import pytest
from helpers_detector import detector_cli

from detector.reproduce.cli import main as reproduce_main
from mpchair.cli import main as mpchair_main
from mpchair.core.limits import MAX_SEED, max_parallel


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
