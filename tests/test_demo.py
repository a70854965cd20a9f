"""``make demo`` runs ``tools/demo.py`` (after the bootstrap): it leaves a synthetic house and a KITTI-format dataset
under its folder, prints where the dataset is, and a second run resumes instead of redoing the frames."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from mpchair.kitti import read_imageset, read_labels, read_velodyne

ROOT = Path(__file__).resolve().parents[1]


def _demo(*args) -> subprocess.CompletedProcess:
    # As `make demo` runs it: the script by path with the venv's python, from another folder. The script does not put
    # the checkout on sys.path (the venv has the package installed in editable mode); PYTHONPATH names this checkout
    # so that its code is the one run even where the venv's editable install points at another checkout.
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, str(ROOT / "tools" / "demo.py"), *map(str, args)], capture_output=True,
                          text=True, env=env, cwd="/", timeout=600)


def test_demo_leaves_a_dataset_and_prints_where(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    res = _demo("--out", out, "--frames", "3", "--workers", "1")
    assert res.returncode == 0, res.stderr
    dataset = out / "dataset"
    lines = res.stdout.splitlines()
    assert lines[0] == str(dataset)
    assert lines[1].startswith(f"{dataset}: 3 frames (complete); this run made 3 in ")
    assert "synthesized house" in res.stderr and f"-> {out / 'houses'}" in res.stderr
    manifest = json.loads((dataset / "manifest.json").read_text())
    (house,) = manifest["houses"]
    assert (out / "houses" / "v1" / "scans" / house).is_dir()
    ids = sorted(sum((read_imageset(dataset / "ImageSets" / f"{s}.txt") for s in ("train", "val", "test")), []))
    assert ids == ["000000", "000001", "000002"] and [r["frame"] for r in manifest["frames"]] == ids
    for rec in manifest["frames"]:
        labels = read_labels(dataset / "training" / "label_2" / f"{rec['frame']}.txt")
        assert list(labels.objects().names) == ["Chair"] * len(rec["kept"]) and rec["kept"]  # no empty frames
        assert len(read_velodyne(dataset / "training" / "velodyne" / f"{rec['frame']}.bin")) == rec["points"] > 0
    before = {p: p.read_bytes() for p in sorted(dataset.rglob("*")) if p.is_file()}

    again = _demo("--out", out, "--frames", "3", "--workers", "1")
    assert again.returncode == 0, again.stderr
    first, second = lines[1], again.stdout.splitlines()[1]
    assert again.stdout.splitlines()[0] == str(dataset)
    # nothing is synthesized again, and the run says so rather than claiming it made the house
    assert "synthesized house" not in again.stderr and f"already in {out / 'houses'} (nothing synthesized)" in (
        again.stderr)
    assert second.startswith(f"{dataset}: 3 frames (complete); nothing needed to be made (3 frames already there); ")
    # the dataset is described from its manifest: the same boxes, rejections, points and splits as the first run
    kept = sum(len(r["kept"]) for r in manifest["frames"])
    assert f"; boxes kept {kept} (chair {kept}), rejected: " in first and kept > 0
    assert second.split("; boxes kept ")[1] == first.split("; boxes kept ")[1]
    assert {p: p.read_bytes() for p in sorted(dataset.rglob("*")) if p.is_file()} == before

    bad = _demo("--out", tmp_path / "bad", "--frames", "0")
    assert bad.returncode == 2 and bad.stderr.splitlines()[-1] == "error: --frames must be >= 1, got 0"
    assert bad.stdout == "" and "Traceback" not in bad.stderr
