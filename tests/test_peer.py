"""``detector bench --peer open3d-ml``: Open3D-ML's own PointPillars as a timing row (detector.bench.peer).

The peer must be our dense network in Open3D-ML's code (same layers, channels, grid, weights), run on the same frames
in the same interleaved loop, and reported in the JSON and the table; without Open3D-ML the option fails with one
``error:`` line.
"""

from __future__ import annotations

import dataclasses
import json
import sys

import numpy as np
import pytest
import torch
from helpers_detector import detector_cli as _cli
from helpers_detector import make_tiny_dataset, write_test_config

import detector.bench.peer as peer_mod
from detector.bench import COMPONENTS, BenchResult, ratio_rows
from detector.checkpoint import load_model
from detector.config import load_experiment
from detector.data.experiment import load_eval_frames
from mpchair.core.errors import InputError

pytest.importorskip("open3d.ml.torch", reason="Open3D-ML (the project's open3d extra) is not installed")


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("peer")
    data = make_tiny_dataset(root / "ds", n_frames=3)
    # 64 points per pillar: no pillar of these frames hits the cap, so both voxelizers keep every point
    dense = write_test_config(root / "dense.yaml", model=dict(max_points_per_pillar=64))
    sparse = write_test_config(root / "sparse.yaml", model=dict(backbone="sparse", max_points_per_pillar=64))
    return data, dense, sparse



def test_peer_is_our_dense_network_in_open3d_ml_code(setup) -> None:
    """Same weights → the same head maps on every frame: the same layers, channels, grid and decorations."""
    data, dense, _ = setup
    cfg = load_experiment(dense)
    ours = load_model(cfg, None, torch.device("cpu"), seed=3)
    peer = peer_mod.build_peer(cfg.model, ours)
    assert type(peer).__module__ == "open3d._ml3d.torch.models.point_pillars"
    assert peer.middle_encoder.output_shape == list(cfg.model.output_shape)
    assert peer.bbox_head.num_anchors == len(cfg.model.anchor_sizes) * len(cfg.model.anchor_rotations)
    m = cfg.model
    for frame in load_eval_frames(cfg, data, "test"):
        # Points exactly on a pillar boundary (these frames have walls at whole multiples of the pillar size) may
        # index differently: Open3D-ML's voxelize works in float32, ours in float64. Leave those out.
        cell = (frame.points[:, :2] - np.float32(m.point_cloud_range[:2])) / np.float32(m.voxel_size[:2])
        inner = (np.abs(cell - np.round(cell)) > 1e-3).all(axis=1)
        assert inner.mean() > 0.6
        pts = torch.from_numpy(frame.points[inner])
        with torch.no_grad():
            mine = ours([pts])
            v, n, c = peer.voxelize([pts])
            theirs = peer.bbox_head(peer.neck(peer.backbone(peer.middle_encoder(peer.voxel_encoder(v, n, c), c, 1))))
        assert int(n.max()) < cfg.model.max_points_per_pillar  # no cap hit: both keep every point
        for a, b in zip(mine, theirs):
            assert a.shape == b.permute(0, 2, 3, 1).shape
            np.testing.assert_allclose(a.numpy(), b.permute(0, 2, 3, 1).numpy(), atol=1e-4)
    # the package placeholders used for the import are gone again
    assert "open3d._ml3d.torch" not in sys.modules or hasattr(sys.modules["open3d._ml3d.torch"], "__file__")


def test_a_different_architecture_is_refused(setup) -> None:
    _, dense, _ = setup
    cfg = load_experiment(dense)
    ours = load_model(cfg, None, torch.device("cpu"))
    other = dataclasses.replace(cfg.model, layer_nums=(1, 1, 2))
    with pytest.raises(InputError, match="differs"):
        peer_mod.build_peer(other, ours)
    with pytest.raises(InputError, match="mirrors a dense model"):
        peer_mod.peer_kwargs(dataclasses.replace(cfg.model, backbone="sparse"))


def test_bench_peer_row_same_frames_json_and_table(setup, tmp_path, capsys, monkeypatch) -> None:
    data, dense, sparse = setup
    seen = []
    real = peer_mod.time_peer_frame

    def spy(peer, points):  # records what the peer is fed, then runs the real timing
        seen.append(points.copy())
        return real(peer, points)

    monkeypatch.setattr(peer_mod, "time_peer_frame", spy)
    out = tmp_path / "bench.json"
    code, stdout, _ = _cli(["bench", "--config", dense, "--config", sparse, "--data", data, "--frames", "2",
                            "--trials", "2", "--warmup", "1", "--threads", "1", "--peer", "open3d-ml",
                            "--json-out", out], capsys)
    assert code == 0
    result = json.loads(out.read_text())
    names = [m["name"] for m in result["models"]]
    assert names == ["dense", "sparse", "open3d-ml"]
    assert [m["peer"] for m in result["models"]] == [None, None, "open3d-ml"]
    assert result["protocol"]["peer"] == "open3d-ml" and result["machine"]["open3d"]
    for m in result["models"]:
        assert set(m["components"]) == set(COMPONENTS)
        assert all(v["mean_ms"] > 0 for v in m["components"].values())
        parts = sum(m["components"][k]["mean_ms"] for k in COMPONENTS[:-1])
        assert m["components"]["total"]["mean_ms"] == pytest.approx(parts, rel=1e-9)
    assert "dense's weights" in result["models"][2]["weights"]
    # the peer saw exactly the dense model's frames: 1 warm-up + 2 trials x 2 frames, in frame order
    frames = load_eval_frames(load_experiment(dense), data, "test", 2)
    expected = [frames[0].points] + [f.points for f in frames] * 2
    assert len(seen) == len(expected) and all(np.array_equal(a, b) for a, b in zip(seen, expected))
    assert [name for name, _ in ratio_rows(BenchResult.from_json(result))] == [
        "dense / sparse", "open3d-ml / dense", "open3d-ml / sparse"]
    assert "open3d-ml / dense" in stdout and "Open3D-ML" in stdout


def test_bench_peer_without_open3d_ml_is_one_error_line(setup, tmp_path, capsys, monkeypatch) -> None:
    data, dense, _ = setup
    monkeypatch.setitem(sys.modules, "open3d.ml.torch", None)  # what a missing extra looks like to import
    monkeypatch.delitem(sys.modules, "open3d._ml3d.torch.models.point_pillars", raising=False)
    out = tmp_path / "bench.json"
    code, _, err = _cli(["bench", "--config", dense, "--data", data, "--frames", "1", "--trials", "1",
                         "--peer", "open3d-ml", "--json-out", out], capsys)
    assert code == 2 and err.startswith("error: ") and err.count("\n") == 1 and "Open3D-ML" in err
    assert not out.exists()
