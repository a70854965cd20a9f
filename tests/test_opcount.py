"""``detector.opcount``: dense counts equal the hand formula / Table I, exact sparse counts equal a brute-force count
from the active sets and never exceed Table I's bound (real-ish scenes and adversarial uniform sites)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from helpers_detector import make_tiny_dataset

from detector.cli import main
from detector.config import load_experiment
from detector.models import build_model
from detector.opcount import count_dataset, dense_counts, format_counts, frame_counts, sparse_counts, table1

SMOKE = "detector/configs/mpchair_sparse_smoke.yaml"
PAPER = "detector/configs/mpchair_sparse.yaml"
K2 = {"3x3 conv": 9, "2x2 conv": 4, "1x1 convT": 1, "2x2 convT": 4, "4x4 convT": 16}


@pytest.fixture(scope="module")
def smoke():
    cfg = load_experiment(SMOKE)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        model = build_model(cfg.model).eval()
    return cfg, model


def _by_type(layers):
    out: dict[str, int] = {}
    for lc in layers:
        out[lc.conv_type] = out.get(lc.conv_type, 0) + lc.macs
    return out


def test_dense_count_is_the_hand_formula_and_table1() -> None:
    cfg = load_experiment(PAPER).model
    h, w = cfg.output_shape  # 768 x 512
    c = 64
    layers = dense_counts(cfg)
    by_type = _by_type(layers)
    chw = c * c * h * w
    # 3x3: stride-2 convs 1/4 + 1/8 + 1/8, stride-1 convs 3/4 + 5/4 + 5/4 (x 9 MACs); transposed 1x1/2x2/4x4
    assert by_type == {"3x3 conv": 9 * 15 * chw // 4, "1x1 convT": chw // 2, "2x2 convT": 4 * chw // 4,
                       "4x4 convT": 16 * chw // 8}
    assert sum(by_type.values()) == 37.25 * chw  # 37.25 * 64^2 * 768 * 512 = 60.0 G MACs
    t1 = table1(0.01, c, h, w)
    for t, macs in by_type.items():
        assert macs == pytest.approx(t1[t]["dense"] * K2[t], rel=1e-12)
    assert len(layers) == (1 + 3) + (1 + 5) + (1 + 5) + 3  # per block a stride-2 conv + L convs; 3 transposed


def test_table1_reproduces_the_papers_percentages() -> None:
    def fewer(d: float) -> float:
        t = table1(d, 64, 768, 512)
        return 1 - sum(v["bound"] for v in t.values()) / sum(v["dense"] for v in t.values())

    assert 0.79 <= fewer(0.00750) < 0.82  # "at least 79% fewer convolutions" (Matterport-Chair median D)
    assert 0.50 <= fewer(0.02459) < 0.55  # "at least 50% fewer" (KITTI median D)
    # D = 1: the three 2x2 down-convs (1/4 + 1/8 + 1/8 convolutions) cost what the dense 3x3 stride-2 ones do, so
    # the bound meets the dense count (the paper: "converges to PointPillars' Backbone")
    assert fewer(1.0) == pytest.approx(0.0, abs=1e-12)


def _brute_force(coords: np.ndarray, shape: tuple[int, int], cfg) -> dict[str, int]:
    """MACs per layer name pattern from plain Python sets: floor(c / 2) parents, 3x3 neighbours, parents of block-1."""
    sets = [{(int(y), int(x)) for y, x in coords}]
    for _ in range(3):
        sets.append({(y // 2, x // 2) for y, x in sets[-1]})
    chans = [cfg.pfn_channels, *cfg.layer_channels]
    total = {"3x3 conv": 0, "2x2 conv": 0, "1x1 convT": 0, "2x2 convT": 0, "4x4 convT": 0}
    for i in range(3):
        total["2x2 conv"] += len(sets[i]) * chans[i] * chans[i + 1]
        nbrs = sum((y + dy, x + dx) in sets[i + 1] for y, x in sets[i + 1] for dy in (-1, 0, 1) for dx in (-1, 0, 1))
        total["3x3 conv"] += cfg.layer_nums[i] * nbrs * chans[i + 1] ** 2
        s = 2**i
        parents = sum((y // s, x // s) in sets[i + 1] for y, x in sets[1])
        total[f"{s}x{s} convT"] += parents * chans[i + 1] * cfg.neck_channels[i]
    return total


def _sites(rng: np.random.Generator, shape: tuple[int, int], n: int, clustered: bool) -> np.ndarray:
    ny, nx = shape
    if not clustered:
        flat = rng.choice(ny * nx, size=n, replace=False)
        return np.stack([flat // nx, flat % nx], axis=1)
    centres = rng.integers(0, [ny, nx], size=(max(1, n // 30), 2))
    pts = centres[rng.integers(0, len(centres), n)] + rng.normal(0, 2.0, size=(n, 2)).round().astype(int)
    pts = np.clip(pts, 0, [ny - 1, nx - 1])
    return np.unique(pts, axis=0)


@pytest.mark.parametrize(("density", "clustered"), [(0.005, False), (0.05, False), (0.3, False), (0.9, False),
                                                    (0.05, True)])
def test_sparse_exact_equals_brute_force_and_stays_under_the_bound(smoke, density: float, clustered: bool) -> None:
    cfg, model = smoke
    m = cfg.model
    rng = np.random.default_rng(int(density * 1000) + clustered)
    yx = _sites(rng, m.output_shape, max(1, int(density * m.output_shape[0] * m.output_shape[1])), clustered)
    coords = torch.from_numpy(np.column_stack([np.zeros(len(yx), dtype=np.int64), yx]).astype(np.int64))
    layers = sparse_counts(model, coords, m)
    assert _by_type(layers) == _brute_force(yx, m.output_shape, m)
    fc = frame_counts(dense_counts(m), layers, len(yx), m, layers[0].out_sites, False)
    d = len(yx) / (m.output_shape[0] * m.output_shape[1])
    t1 = table1(d, 64, *m.output_shape)
    for t, v in fc["by_type"].items():
        assert v["sparse"] <= v["bound"], t
        assert v["bound"] == pytest.approx(t1[t]["bound"] * K2[t], rel=1e-9)  # per-layer bound == Table I literally
        assert v["dense"] == pytest.approx(t1[t]["dense"] * K2[t], rel=1e-12)
    assert fc["total"]["sparse"] <= fc["total"]["bound"] <= fc["total"]["dense"] * (1 + 1e-12) + 1


def _cli(capsys, *args) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in args])
    out, err = capsys.readouterr()
    return e.value.code, out, err


def test_count_dataset_on_scenes(tmp_path, capsys) -> None:
    data = make_tiny_dataset(tmp_path / "ds", n_frames=3)
    result = count_dataset(SMOKE, data, "test", frames=3)
    # `detector ops`: the same counts as JSON on stdout and in --out; tables (plain or Markdown) otherwise; --start
    # picks the first frame counted.
    code, out, _ = _cli(capsys, "ops", "--config", SMOKE, "--data", data, "--frames", "3", "--json", "--out",
                        tmp_path / "ops.json")
    assert code == 0 and json.loads(out) == json.loads((tmp_path / "ops.json").read_text())
    assert json.loads(out) == json.loads(json.dumps(result))
    one = count_dataset(SMOKE, data, "test", frames=1, start=2)
    assert one["frames"] == result["frames"][2:]
    code, out, _ = _cli(capsys, "ops", "--config", SMOKE, "--data", data, "--frames", "1", "--start", "2",
                        "--markdown")
    assert code == 0 and out == format_counts(one, markdown=True) + "\n"
    assert "| 000002 |" in out and "000001" not in out
    code, out, _ = _cli(capsys, "ops", "--config", SMOKE, "--data", data, "--frames", "1", "--start", "2")
    assert code == 0 and out == format_counts(one) + "\n" and not out.startswith("|")
    code, _, err = _cli(capsys, "ops", "--config", SMOKE, "--data", data, "--frames", "0", "--out",
                        tmp_path / "none.json")
    assert code == 2 and err.startswith("error: need --frames >= 1") and not (tmp_path / "none.json").exists()
    assert [f["frame_id"] for f in result["frames"]] == ["000000", "000001", "000002"]
    for f in result["frames"]:
        assert f["pillars"] > 100
        for v in f["by_type"].values():
            assert 0 < v["sparse"] <= v["bound"]
        assert f["total"]["sparse"] < f["total"]["dense"]
        assert f["active_sites"]["block1"] < f["pillars"]  # floor(c / 2) merges neighbours of real scenes
    s = result["summary"]
    assert s["sparse_over_bound"]["max"] <= 1.0 and s["max_type_sparse_over_bound"] <= 1.0
    assert s["paper_architecture"] and 0 < s["table1_fewer_convolutions_at_least"] < 1
    # Sparse+WideConv: the first SubM of each block is 9x9 (reach 4): the two block-3 sites (1, 1) and (5, 3) see
    # each other, the block-1/2 sites are isolated
    wide = replace(load_experiment(SMOKE).model, backbone="sparse_wide")
    with torch.random.fork_rng(devices=[]):
        model = build_model(wide).eval()
    coords = torch.tensor([[0, 10, 10], [0, 10, 11], [0, 40, 30]])
    types = _by_type(sparse_counts(model, coords, wide))
    assert types["9x9 conv"] == 2 * 64 * 64 + 2 * 128 * 128 + 4 * 256 * 256


def test_sparse_computed_counts_the_form_the_engine_runs(smoke) -> None:
    """``sparse_computed`` is what the engine multiplies in the form it takes: in fp32 inference with oneDNN the
    one-GEMM SubM form at any fill (all k^2 taps of every site) and the transposed conv's GEMM form (every coarse site
    times all s^2 slots); under MKL "auto" picks by fill, and a low-fill SubM / level takes the rulebook (exact)."""
    from detector.ops.gemm import HAVE_ONEDNN, gemm_backend

    cfg, model = smoke
    m = cfg.model
    rng = np.random.default_rng(7)
    yx = _sites(rng, m.output_shape, 40, clustered=False)  # isolated sites: fill ~1/9, so the forms differ
    coords = torch.from_numpy(np.column_stack([np.zeros(len(yx), dtype=np.int64), yx]).astype(np.int64))
    with gemm_backend("mkl"):
        mkl = sparse_counts(model, coords, m)
    layers = sparse_counts(model, coords, m)
    for lc, lm in zip(layers, mkl):
        cc = lc.c_in * lc.c_out
        if lc.kind == "sparse_down":
            assert lc.macs_computed == lm.macs_computed == lc.out_sites * 4 * cc
        elif lc.kind == "sparse_convT" and lc.kernel == 1:
            assert lc.macs_computed == lm.macs_computed == lc.macs == lc.in_sites * cc
        elif lc.kind == "sparse_convT":
            assert lm.macs_computed == lm.macs  # fewer than half the products needed: the rulebook
            if HAVE_ONEDNN:
                assert lc.macs_computed == lc.in_sites * lc.kernel**2 * cc > lc.macs
        else:
            assert lm.macs_computed == lm.macs  # fill < 0.7: the rulebook
            if HAVE_ONEDNN:
                assert lc.macs_computed == lc.in_sites * 9 * cc > lc.macs
