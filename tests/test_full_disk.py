"""Full disks under the commands the third audit (issue 47) left: ``stream-eval --save-results`` (it left empty
``res/00/`` folders), ``detector export`` and the exported graphs ``eval --runtime`` / ``bench`` keep in ``TMPDIR``
(each said ``error: No space left on device`` with no path). Each now ends with one line naming the path the user
gave (or the temporary folder, and ``TMPDIR``), exit 2, and leaves nothing it made. A real ENOSPC: a small tmpfs,
which needs the right to mount (root with CAP_SYS_ADMIN; skipped elsewhere)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from helpers_detector import detector_cli, make_tiny_dataset, write_test_config
from helpers_faults import mounted_tmpfs, tree
from helpers_recordings import small_stream

ROOT = Path(__file__).resolve().parents[1]


def _fill(disk: Path, leave: int = 0) -> None:
    """Fill the tmpfs ``disk`` with a file ``filler`` up to ``leave`` bytes of room."""
    st = os.statvfs(disk)
    (disk / "filler").write_bytes(b"\0" * (st.f_bavail * st.f_frsize - leave))


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    return lines[0]


@pytest.fixture
def tiny_disk(tmp_path):
    with mounted_tmpfs(tmp_path / "disk", "256k") as disk:
        yield disk


def _save(data: Path, out: Path, capsys, *extra: str) -> tuple[int, str]:
    code, _, err = detector_cli(["stream-eval", "--data", data, "--oracle", "--latency-ms", "0", "--quiet",
                                 "--save-results", out, *extra], capsys)
    return code, err


@pytest.mark.parametrize("room", [0, 8 << 10])
def test_save_results_on_a_full_disk_leaves_no_folder(tmp_path, tiny_disk, capsys, room):
    """Full from the start, or filling up after the first file: one line naming the folder asked for, exit 2, and
    neither it, nor its work folder, nor the parent folders the run made."""
    data = small_stream(tmp_path / "st")
    _fill(tiny_disk, room)
    for out in (tiny_disk / "res", tiny_disk / "a" / "b" / "res"):
        code, err = _save(data, out, capsys)
        assert code == 2 and _one_line(err) == f"error: {out}: No space left on device; no result file was saved"
        assert sorted(p.name for p in tiny_disk.iterdir()) == ["filler"]


def test_save_results_replaces_only_its_own_folder(tmp_path, capsys):
    """With room the same command saves the files; again, it replaces its own folder; a folder holding anything else,
    or the --results folder it reads, is refused before any work and left as it was."""
    data = small_stream(tmp_path / "st")
    out = tmp_path / "res"
    code, err = _save(data, out, capsys)
    assert code == 0, err
    saved = tree(out)
    assert sorted(saved) == [".mpchair-output.json", "00/000000.txt", "00/000001.txt"]
    assert saved["00/000001.txt"].startswith(b"Chair ")
    assert _save(data, out, capsys)[0] == 0 and tree(out) == saved
    (out / "00" / "notes.txt").write_text("mine")
    code, err = _save(data, out, capsys)
    assert code == 2 and _one_line(err).startswith(f"error: {out}: will not replace this folder: it holds 00/notes.txt")
    assert tree(out) == {**saved, "00/notes.txt": b"mine"}
    (out / "00" / "notes.txt").unlink()
    code, err = _save(data, out, capsys, "--results", out)
    assert code == 2 and "is the --results folder this run reads" in _one_line(err)
    # a folder saved before ownership markers (result files only) is recognised as this command's
    (out / ".mpchair-output.json").unlink()
    assert _save(data, out, capsys)[0] == 0 and tree(out) == saved
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res", "st"]


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    """(config, checkpoint, dataset): the slim test network with its initial weights, and 4 frames."""
    import torch

    from detector.checkpoint import Checkpoint, save_checkpoint
    from detector.config import load_experiment
    from detector.models import build_model

    base = tmp_path_factory.mktemp("model")
    cfg = write_test_config(base / "cfg.yaml")
    torch.manual_seed(0)
    ckpt = base / "w.pt"
    save_checkpoint(ckpt, Checkpoint(model=build_model(load_experiment(cfg).model).state_dict()))
    return cfg, ckpt, make_tiny_dataset(base / "ds", n_frames=4)


def test_an_export_on_a_full_disk_names_the_folder_and_keeps_the_older_export(model, tmp_path, capsys):
    pytest.importorskip("onnx")
    cfg, ckpt, _ = model
    with mounted_tmpfs(tmp_path / "disk", "64m") as disk:
        out = disk / "exp"
        args = ["export", "--config", cfg, "--checkpoint", ckpt, "--format", "onnx", "--out", out]
        code, _, err = detector_cli(args, capsys)
        assert code == 0, err
        older = tree(disk)
        for room in (16 << 10, 0):  # the graph's write fails / the lock's first write fails
            _fill(disk, room)
            code, _, err = detector_cli(args, capsys)
            assert code == 2 and _one_line(err).startswith(f"error: {out}: No space left on device"), err
            (disk / "filler").unlink()
            assert tree(disk) == older  # the older export as it was; no work folder, no lock file


@pytest.mark.parametrize("command", ["eval", "bench"])
def test_a_full_tmpdir_under_a_deployed_eval_names_the_temporary_folder(model, tmp_path, tiny_disk, command):
    """``eval --runtime onnxruntime`` and ``bench --runtime onnxruntime`` export the graph into a temporary folder
    under TMPDIR: a full TMPDIR is one line naming the file there and saying so (the third audit: no path)."""
    pytest.importorskip("onnxruntime")
    cfg, ckpt, data = model
    _fill(tiny_disk, 16 << 10)  # room for Python's probe of TMPDIR (a TMPDIR it cannot write is skipped), not the graph
    args = {"eval": ["--out", tmp_path / "ev"],
            "bench": ["--split", "val", "--frames", "1", "--trials", "1", "--warmup", "0", "--no-progress"]}[command]
    res = subprocess.run([sys.executable, "-m", "detector.cli", command, "--config", cfg, "--data", data,
                          "--checkpoint", ckpt, "--runtime", "onnxruntime", "--threads", "1", *map(str, args)],
                         capture_output=True, text=True, timeout=600,
                         env={**os.environ, "TMPDIR": str(tiny_disk), "PYTHONPATH": str(ROOT)})
    line = _one_line(res.stderr)
    assert res.returncode == 2 and line.startswith(f"error: {tiny_disk}/detector-{command}-"), line
    assert "No space left on device (a temporary folder for the exported graphs: free space there or set TMPDIR" in line
    assert sorted(p.name for p in tiny_disk.iterdir()) == ["filler"] and not (tmp_path / "ev").exists()
