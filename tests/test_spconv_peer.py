"""spconv as a peer (detector/bench/spconv_peer.py, tools/bench_spconv.py): the weight conversions follow spconv's
layouts, our engine equals the masked dense chain, the comparison helpers catch differences; with spconv installed
(the optional ``spconv`` extra) its rebuild of our backbone + neck equals ours in float64 and the tool runs."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from detector.bench import spconv_peer as peer
from detector.models.sparse_backbone import SparseBackboneNeck
from mpchair.core.errors import InputError
from tests.helpers_tools import load_tool

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "models" / "mpchair_sparse_smoke.yaml"
SHAPE = (32, 24)
SMALL = dict(in_channels=5, layer_channels=(4, 6, 8), layer_nums=(1, 2, 1), out_channels=(3, 3, 3))


@pytest.fixture
def threads():
    """Restore torch's thread count after a test that sets it."""
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def small_model(seed: int = 0) -> SparseBackboneNeck:
    torch.manual_seed(seed)
    model = SparseBackboneNeck(**SMALL).eval()
    peer.randomise_batchnorm_(model, seed + 1)
    return model


def small_frame(seed: int = 0) -> peer.SiteFrame:
    return peer.synthetic_frames(SHAPE, 0.15, 1, 5, seed)[0]


# --- without spconv ------------------------------------------------------------------------------------------------

def _shifted(x: torch.Tensor, dy: int, dx: int) -> torch.Tensor:
    """``x`` (B, C, H, W) read at (y + dy, x + dx), zero outside."""
    p = max(abs(dy), abs(dx))
    xp = F.pad(x, (p, p, p, p))
    h, w = x.shape[2:]
    return xp[:, :, p + dy : p + dy + h, p + dx : p + dx + w]


def test_krsc_conv_layout_gives_dense_conv() -> None:
    """spconv's conv on a KRSC weight: output q sums tap (ky, kx)'s (O, C) matrix W[:, ky, kx, :] times the input at
    q + (ky, kx) - padding; with conv_krsc's weight that is F.conv2d of our weight (a 3x2 kernel: a swap of the two
    kernel axes would fail)."""
    g = torch.Generator().manual_seed(0)
    w = torch.randn(4, 3, 3, 2, generator=g, dtype=torch.float64)
    x = torch.randn(1, 3, 7, 6, generator=g, dtype=torch.float64)
    k = peer.conv_krsc(w)
    assert k.shape == (4, 3, 2, 3) and k.is_contiguous()
    out = sum(torch.einsum("oc,bchw->bohw", k[:, ky, kx, :], _shifted(x, ky - 1, kx)) for ky in range(3)
              for kx in range(2))
    ref = F.conv2d(F.pad(x, (0, 1, 1, 1)), w)
    torch.testing.assert_close(out, ref, atol=1e-12, rtol=0)


def test_transposed_layouts_give_conv_transpose() -> None:
    """spconv's inverse / transposed conv on a KRSC weight: child s*p + (ky, kx) of coarse site p gets
    W[:, ky, kx, :] @ x[p]; with transposed_krsc that is F.conv_transpose2d. The 1x1 weight, read as spconv's 1x1
    path reads it (an (in, out) matrix), is the same product."""
    g = torch.Generator().manual_seed(1)
    s = 4
    wt = torch.randn(3, 5, s, s, generator=g, dtype=torch.float64)  # (C, O, s, s)
    x = torch.randn(1, 3, 2, 3, generator=g, dtype=torch.float64)
    k = peer.transposed_krsc(wt)
    assert k.shape == (5, s, s, 3)
    out = torch.zeros(1, 5, 2 * s, 3 * s, dtype=torch.float64)
    for ky in range(s):
        for kx in range(s):
            out[:, :, ky::s, kx::s] = torch.einsum("oc,bchw->bohw", k[:, ky, kx, :], x)
    torch.testing.assert_close(out, F.conv_transpose2d(x, wt, stride=s), atol=1e-12, rtol=0)
    w1 = torch.randn(3, 5, 1, 1, generator=g, dtype=torch.float64)
    rows = x[0].flatten(1).t()  # (sites, C)
    one = peer.one_by_one_weight(w1)
    assert one.shape == (5, 1, 1, 3)
    torch.testing.assert_close(rows @ one.view(3, 5), F.conv_transpose2d(x, w1)[0].flatten(1).t(), atol=1e-12,
                               rtol=0)


def test_ours_equals_masked_dense_chain() -> None:
    """Our engine in float64 equals the dense chain to rounding, per block and on the neck rows; float32 within
    float32 rounding of it (without spconv)."""
    model = small_model()
    frame = small_frame()
    e = peer.exactness(model, frame, SHAPE, with_spconv=False)
    assert len(e["sites"]) == 3 and e["sites"][0] > e["sites"][1] > e["sites"][2] > 0
    d64, d32 = e["float64"]["ours_vs_dense"], e["float32"]["ours_vs_dense64"]
    assert max(d64["blocks"]) < 1e-12 and d64["neck"] < 1e-12
    assert max(d32["blocks"]) < 1e-4 and d32["neck"] < 1e-4
    assert "spconv_vs_ours" not in e["float64"]
    # the model was not changed (exactness works on copies)
    assert next(model.parameters()).dtype == torch.float32


def test_dense_chain_sees_a_changed_weight() -> None:
    """The comparison is not vacuous: the dense chain of a model with one changed SubM weight differs from ours."""
    model = small_model().double()
    other = small_model().double()
    with torch.no_grad():
        other.blocks[1][3].weight[0, 0, 0, 0] += 1.0  # block 2's first SubM, tap (0, 0)
    frame = small_frame()
    ours = peer.run_ours(model, frame, SHAPE, torch.float64)
    shapes = [(SHAPE[0] >> i, SHAPE[1] >> i) for i in (1, 2, 3)]
    same = peer._diffs(ours, peer._dense_outputs(model, frame, SHAPE, ours), shapes)
    changed = peer._diffs(ours, peer._dense_outputs(other, frame, SHAPE, ours), shapes)
    assert max(same["blocks"]) < 1e-12
    assert changed["blocks"][0] < 1e-12 and changed["blocks"][1] > 1e-3 and changed["neck"] > 1e-3


def test_site_helpers() -> None:
    g = torch.Generator().manual_seed(2)
    coords = small_frame().coords
    feats = torch.randn(coords.shape[0], 4, generator=g)
    perm = torch.randperm(coords.shape[0], generator=g)
    assert peer.max_abs_on_sites(coords, feats, coords[perm], feats[perm], SHAPE) == 0.0
    bumped = feats[perm].clone()
    bumped[0, 1] += 0.5
    assert peer.max_abs_on_sites(coords, feats, coords[perm], bumped, SHAPE) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="site sets differ"):
        peer.max_abs_on_sites(coords, feats, coords[1:], feats[1:], SHAPE)
    rows = peer.select_rows(coords[perm].int(), coords[:7], SHAPE)
    assert torch.equal(coords[perm][rows], coords[:7])
    a = [feats, feats[:3]]
    assert peer.same_outputs(a, [t.clone() for t in a]) == (True, 0.0)
    equal, diff = peer.same_outputs(a, [bumped, feats[:3]])
    assert not equal and diff > 0
    assert peer.same_outputs(a, [feats]) == (False, float("inf"))


@pytest.mark.parametrize("kwargs, match", [
    (dict(sparse_blocks=2), "all-sparse"),
    (dict(down_kernel=9), "2x2 stride-2"),
    (dict(downsample="reference_quirk"), "2x2 stride-2"),
])
def test_inexpressible_backbones_are_refused(kwargs: dict, match: str) -> None:
    model = SparseBackboneNeck(**SMALL, **kwargs)
    with pytest.raises(InputError, match=match):
        peer.check_expressible(model)


def test_missing_spconv_is_one_line(monkeypatch, capsys) -> None:
    """Where spconv cannot be imported, the module and the tool say how to install it (one line, exit 2)."""
    monkeypatch.setitem(sys.modules, "spconv", None)
    monkeypatch.setitem(sys.modules, "spconv.pytorch", None)
    with pytest.raises(InputError, match=r"pip install .*\[spconv\]"):
        peer.import_spconv()
    tool = load_tool("bench_spconv")
    assert tool.main(["--config", str(SMOKE), "--density", "0.05", "--frames", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "[spconv]" in err[0]


@pytest.mark.parametrize("args, match", [
    (["--threads", "0"], "--threads"),
    (["--threads", "one"], "--threads"),
    (["--frames", "0"], "--frames"),
    (["--density", "2"], "--density"),
])
def test_tool_bad_arguments(args: list[str], match: str, capsys, tmp_path: Path) -> None:
    tool = load_tool("bench_spconv")
    base = ["--config", str(SMOKE), "--density", "0.05"]
    assert tool.main([*base, *args, "--json-out", str(tmp_path / "r.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and match in err[0]
    assert not (tmp_path / "r.json").exists()


# --- with spconv ---------------------------------------------------------------------------------------------------

def test_spconv_rebuild_equals_ours_in_float64(threads) -> None:
    """spconv's rebuild of our backbone + neck (same weights, same sites) equals ours to float64 rounding, every block
    and the neck rows, at 1 thread (at 2, spconv 2.3.8's CPU results are wrong in some calls: docs/sparse.md)."""
    pytest.importorskip("spconv.pytorch")
    torch.set_num_threads(1)
    e = peer.exactness(small_model(), small_frame(), SHAPE)
    sp = e["float64"]["spconv_vs_ours"]
    assert max(sp["blocks"]) < 1e-12 and sp["neck"] < 1e-12
    assert max(e["float32"]["spconv_vs_dense64"]["blocks"]) < 1e-4


def test_tool_end_to_end(threads, tmp_path: Path, capsys) -> None:
    """The tool on the smoke grid: a header naming what the numbers depend on, both engines timed, our engine
    bit-identical run to run and equal to dense convolution, spconv equal to ours at 1 thread."""
    pytest.importorskip("spconv.pytorch")
    tool = load_tool("bench_spconv")
    out = tmp_path / "r.json"
    assert tool.main(["--config", str(SMOKE), "--density", "0.03", "--frames", "2", "--trials", "2", "--threads", "1",
                      "--json-out", str(out)]) == 0
    text = capsys.readouterr().out
    for word in ("runtime eager PyTorch", "precision float32", "threads [1]", "allocator", "density D"):
        assert word in text
    r = json.loads(out.read_text())
    assert r["header"]["grid"] == [96, 64] and r["header"]["density"]["frames"] == 2
    assert r["header"]["density"]["median"] == pytest.approx(0.03, abs=2e-4)
    for part in ("blocks", "backbone_neck"):
        row = r["timings"]["1"][part]
        assert row["ours"]["deterministic"] and row["ours"]["max_run_to_run_diff"] == 0.0
        assert row["ours"]["mean_ms"] > 0 and row["spconv"]["mean_ms"] > 0
        assert row["spconv_over_ours"] == pytest.approx(row["spconv"]["mean_ms"] / row["ours"]["mean_ms"])
    (e,) = r["exactness"]["1"].values()
    assert max(e["float64"]["ours_vs_dense"]["blocks"]) < 1e-12
    assert e["float64"]["spconv_vs_ours"]["neck"] < 1e-12
