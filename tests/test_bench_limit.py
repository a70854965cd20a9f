"""``detector.bench.limit`` and ``tools/bench_limit.py`` (issue 49, target 2) at tiny sizes: the exact and GEMM-form
MAC counts against a brute-force count from plain Python sets, the engine's phases covering a forward, the JSON's
documented keys and one-line errors. No timing is asserted (the tool's numbers come from a quiet machine)."""

from __future__ import annotations

import json
from dataclasses import fields

import numpy as np
import pytest
import torch
from helpers_tools import load_tool

from detector.bench import limit
from detector.bench.limit import (
    HEADER_KEYS,
    SUMMARY_KEYS,
    ConvRate,
    FrameWork,
    LayerWork,
    PhaseRow,
    ThreadRun,
    frame_work,
    main,
    phase_rows,
)
from detector.bench.spconv_peer import SiteFrame
from detector.checkpoint import load_model
from detector.config import load_experiment
from detector.ops.gemm import HAVE_ONEDNN, bucket_rows
from detector.sparse import Workspace
from detector.sparse.phases import _NO_PHASE, OTHER, PHASES, PhaseRecorder, phase, recording

SMOKE = "detector/configs/mpchair_sparse_smoke.yaml"  # 96 x 64 grid, the full 64/128/256 x 3/5/5 network


@pytest.fixture(scope="module")
def smoke():
    cfg = load_experiment(SMOKE)
    return cfg, load_model(cfg, None, "cpu", seed=0)


def _frame(seed: int, shape: tuple[int, int], n: int, channels: int) -> tuple[SiteFrame, set[tuple[int, int]]]:
    """Random sites (a few clusters and some isolated ones) with features; and the same sites as a set."""
    rng = np.random.default_rng(seed)
    centres = rng.integers(0, shape, size=(4, 2))
    pts = np.concatenate([centres[rng.integers(0, 4, n)] + rng.normal(0, 2.5, (n, 2)).round().astype(int),
                          rng.integers(0, shape, size=(n // 4, 2))])
    yx = np.unique(np.clip(pts, 0, np.array(shape) - 1), axis=0)
    coords = torch.from_numpy(np.column_stack([np.zeros(len(yx), dtype=np.int64), yx]))
    feats = torch.rand(len(yx), channels, generator=torch.Generator().manual_seed(seed))
    return SiteFrame(f"random-{seed}", feats, coords), {(int(y), int(x)) for y, x in yx}


def _brute_force(sites: set[tuple[int, int]], cfg) -> tuple[int, int, int]:
    """(exact, GEMM-form, executed) MACs of the sparse backbone + neck from Python sets, without ``detector.sparse``:
    floor(c/2) parents per block, 3x3 neighbours on each block's set, each block-1 site's parent on the level's set;
    executed: the GEMM forms' row counts rounded up to oneDNN's buckets (the transposed levels' + 1 zero row)."""
    m = cfg.model
    chans = [m.pfn_channels, *m.layer_channels]
    grids = [tuple(m.output_shape)]
    sets = [sites]
    exact = gemm = executed = 0
    for i in range(len(m.layer_channels)):
        h, w = grids[-1][0] // 2, grids[-1][1] // 2
        down = {(y // 2, x // 2) for y, x in sets[-1] if y // 2 < h and x // 2 < w}
        cc = chans[i] * chans[i + 1]
        exact += sum(1 for y, x in sets[-1] if y // 2 < h and x // 2 < w) * cc  # one tap per input
        gemm += len(down) * 4 * cc  # (M, 4 C) x (4 C, O)
        executed += bucket_rows(len(down)) * 4 * cc
        pairs = sum((y + dy, x + dx) in down for y, x in down for dy in (-1, 0, 1) for dx in (-1, 0, 1))
        exact += m.layer_nums[i] * pairs * chans[i + 1] ** 2
        gemm += m.layer_nums[i] * len(down) * 9 * chans[i + 1] ** 2
        executed += m.layer_nums[i] * bucket_rows(len(down)) * 9 * chans[i + 1] ** 2
        sets.append(down)
        grids.append((h, w))
    block1 = sets[1]
    for i, (c_out, u) in enumerate(zip(m.neck_channels, m.upsample_strides)):
        cc = m.layer_channels[i] * c_out
        exact += sum((y // u, x // u) in sets[i + 1] for y, x in block1) * cc
        gemm += (len(block1) if u == 1 else len(sets[i + 1]) * u * u) * cc  # every coarse site x every slot
        executed += (bucket_rows(len(block1)) if u == 1 else bucket_rows(len(sets[i + 1]) + 1) * u * u) * cc
    return exact, gemm, executed


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_exact_and_gemm_macs_equal_a_brute_force_count(smoke, seed: int) -> None:
    cfg, net = smoke
    frame, sites = _frame(seed, tuple(cfg.model.output_shape), 60 + 40 * seed, cfg.model.pfn_channels)
    work, layers = frame_work(net, cfg, frame)
    exact, gemm, executed = _brute_force(sites, cfg)
    assert work.exact_macs == exact
    if HAVE_ONEDNN:  # fp32 inference takes every GEMM form in oneDNN (else "auto" may take a rulebook)
        assert work.gemm_macs == gemm and work.executed_macs == executed
    assert work.exact_macs < work.gemm_macs <= work.executed_macs
    assert work.pillars == len(sites) and len(work.sites) == 3
    assert sum(lc.macs for lc in layers) == work.exact_macs


def test_phases_cover_the_forward_and_change_nothing(smoke) -> None:
    cfg, net = smoke
    frame, _ = _frame(3, tuple(cfg.model.output_shape), 120, cfg.model.pfn_channels)
    assert phase("gemm") is _NO_PHASE  # no recorder: the shared no-op
    net.workspace = Workspace()
    try:
        with torch.no_grad():
            plain = net.backbone_neck(net.feature_net(frame.features, frame.coords, 1))[0].clone()
            rec = PhaseRecorder(labels=True)
            with recording(rec):
                for _ in range(2):
                    rec.begin()
                    out = net.backbone_neck(net.feature_net(frame.features, frame.coords, 1))[0]
                    rec.end()
    finally:
        net.workspace = None
    assert torch.equal(out, plain)  # the labels change no value
    assert phase("gemm") is _NO_PHASE  # the recorder ends with its block
    for name in PHASES:  # every op kind ran under its label
        assert rec.calls[name] > 0 and rec.seconds[name] > 0, name
    # exclusive times: the phases and the time between them add up to the recorded wall time
    assert sum(rec.seconds.values()) == pytest.approx(rec.total, rel=1e-9)
    rows, total_ms = phase_rows(rec, 2)
    assert [r.phase for r in rows] == [*PHASES, OTHER]
    assert total_ms == pytest.approx(1e3 * rec.total / 2, rel=1e-9)
    assert sum(r.share for r in rows) == pytest.approx(1.0)


def test_recorder_nests_and_rejects_unknown_names() -> None:
    rec = PhaseRecorder()
    with recording(rec):
        rec.begin()
        with phase("gather"):
            with phase("table"):
                pass
        rec.end()
        with pytest.raises(ValueError, match="unknown phase"):
            with phase("convolve"):
                pass
    assert rec.calls["gather"] == rec.calls["table"] == 1
    assert sum(rec.seconds.values()) == pytest.approx(rec.total, rel=1e-9)


def _names(cls) -> set[str]:
    return {f.name for f in fields(cls)}


def test_tool_json_has_the_documented_keys(tmp_path, capsys) -> None:
    out = tmp_path / "limit.json"
    code = main(["--config", SMOKE, "--frames", "1", "--threads", "1", "--repeats", "1", "--profile-repeats", "1",
                 "--warmup", "0", "--json-out", str(out)])
    printed = capsys.readouterr().out
    assert code == 0
    d = json.loads(out.read_text())
    assert set(d) == {"header", "frames", "layers", "runs", "summary"}
    assert set(d["header"]) == set(HEADER_KEYS) and set(d["summary"]) == set(SUMMARY_KEYS)
    assert [set(f) for f in d["frames"]] == [_names(FrameWork)]
    assert all(set(lw) == _names(LayerWork) for lw in d["layers"]) and len(d["layers"]) == 3 + 13 + 3
    (run,) = d["runs"]
    assert set(run) == _names(ThreadRun) and run["threads"] == 1
    assert all(set(c) == _names(ConvRate) for c in run["dense"]) and len(run["dense"]) == 3
    assert [p["phase"] for p in run["phases"]] == [*PHASES, OTHER]
    assert all(set(p) == _names(PhaseRow) for p in run["phases"])
    assert d["summary"]["exact_macs_median"] == d["frames"][0]["exact_macs"]
    assert set(d["summary"]["ratio"]) == {"1"}
    assert "exact MACs per frame (median)" in printed and "| gemm |" in printed


@pytest.mark.parametrize("args", [["--threads", "0"], ["--threads", "a,b"], ["--frames", "0"], ["--frames", "x"],
                                  ["--density", "2"], ["--bogus"], ["--config", "no/such.yaml"],
                                  ["--config", "detector/configs/mpchair_dense_smoke.yaml"],
                                  ["--json-out", "/proc/no/such/dir/x.json"]])
def test_bad_arguments_give_one_line_and_exit_2(args, capsys) -> None:
    assert main([*args, "--repeats", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "\n" not in err


def test_help(capsys) -> None:
    with pytest.raises(SystemExit) as e:
        limit.parser().parse_args(["--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    for flag in ("--threads", "--repeats", "--profile-repeats", "--json-out"):
        assert flag in text


def test_tool_is_the_packages_front_end() -> None:
    assert load_tool("bench_limit").main is main
