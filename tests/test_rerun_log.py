"""Rerun recordings: ``mpchair view --rerun`` (a stream, a dataset) and ``detector stream-eval --rerun``, read back with
rerun's own reader (entities, rows per frame); and one clear error line when rerun-sdk is missing."""

from __future__ import annotations

import os
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest
from helpers_recordings import make_recording_inputs

rr = pytest.importorskip("rerun")
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """A stream (2 episodes, 6 frames each at 1 Hz) and a 3-frame dataset of one synthetic house."""
    return make_recording_inputs(tmp_path_factory.mktemp("rerun"))


def _rows(path: Path) -> Counter:
    """Rows logged per entity path (static rows included), read back with rerun's own RRD reader."""
    store = rr.chunk.RrdReader(str(path)).store()
    rows: Counter = Counter()
    for chunk in store.stream():
        rows[str(chunk.entity_path)] += chunk.num_rows
    return rows


def _cli(module: str, *args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True, timeout=600,
                          env={**os.environ, "PYTHONPATH": str(ROOT), **(env or {})})


def test_stream_recording_has_every_frame(folders, tmp_path):
    res = _cli("mpchair.cli", "view", str(folders / "stream"), "--rerun", str(tmp_path / "s.rrd"))
    assert res.returncode == 0, res.stderr
    rows = _rows(tmp_path / "s.rrd")
    for seq in ("00", "01"):
        for entity in ("sensor", "sensor/points", "sensor/labels", "sensor/dontcare"):
            assert rows[f"/world/{seq}/{entity}"] == 6  # 5 s at 1 Hz: frames at 0..5 s
        assert rows[f"/world/{seq}/trajectory"] == 1
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_dataset_recording(folders, tmp_path):
    res = _cli("mpchair.cli", "view", str(folders / "dataset"), "--rerun", str(tmp_path / "d.rrd"), "--limit", "2")
    assert res.returncode == 0, res.stderr
    rows = _rows(tmp_path / "d.rrd")
    assert rows["/world/frames/sensor"] == rows["/world/frames/sensor/points"] == 2
    assert rows["/world/frames/sensor/labels"] == 2


def test_stream_eval_recording_adds_the_detector_boxes(folders, tmp_path):
    res = _cli("detector.cli", "stream-eval", "--data", str(folders / "stream"), "--oracle", "--latency-ms", "1500",
               "--rerun", str(tmp_path / "e.rrd"), "--quiet")
    assert res.returncode == 0, res.stderr
    rows = _rows(tmp_path / "e.rrd")
    for seq in ("00", "01"):
        assert rows[f"/world/{seq}/sensor/detections/raw"] == rows[f"/world/{seq}/sensor/detections/ego"] == 6
        assert rows[f"/world/{seq}/sensor/labels"] == 6


def test_missing_rerun_is_one_error_line(folders, tmp_path):
    # a sitecustomize that hides rerun-sdk, as on an install without the extra
    (tmp_path / "sitecustomize.py").write_text("import sys\nsys.modules['rerun'] = None\n")
    env = {"PYTHONPATH": f"{tmp_path}{os.pathsep}{ROOT}"}
    for module, args in (("mpchair.cli", ["view", str(folders / "stream"), "--rerun", str(tmp_path / "x.rrd")]),
                         ("detector.cli", ["stream-eval", "--data", str(folders / "stream"), "--oracle",
                                           "--latency-ms", "0", "--rerun", str(tmp_path / "x.rrd")])):
        res = subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True, timeout=600,
                             env={**os.environ, **env})
        assert res.returncode == 2 and res.stderr.strip().splitlines() == [
            "error: --rerun needs rerun-sdk, which is not installed; install the rerun extra: "
            "pip install -e '.[rerun]' (rerun-sdk==0.41.0)"]
    assert not (tmp_path / "x.rrd").exists()
    res = _cli("mpchair.cli", "view", str(folders / "stream"), "--rerun", str(tmp_path / "x.png"))
    assert res.returncode == 2 and "--rerun must name a .rrd file" in res.stderr
