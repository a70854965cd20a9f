"""``detector bench --runs N`` (issue 48, item 3): the bench repeated in separate processes, each ratio as the median
with its min-max over the runs (known answers on fixture results), and a tiny real run of two processes (no timed
assertion: only the shape and the consistency of what it reports)."""

from __future__ import annotations

import json

import click.testing
import pytest
from helpers_detector import make_tiny_dataset

from detector.bench.repeat import Repeated, Spread, child_args, format_repeated, repeated
from detector.bench.result import BenchResult
from detector.cli import cli
from mpchair.core.errors import InputError

DENSE = "detector/configs/mpchair_dense_smoke.yaml"
SPARSE = "detector/configs/mpchair_sparse_smoke.yaml"


def _result(dense_ms: float, sparse_ms: float, names=("dense", "sparse")) -> BenchResult:
    """A bench result of two rows whose backbone is half the total."""
    def row(name: str, ms: float) -> dict:
        return {"name": name, "components": {"backbone": {"mean_ms": ms / 2, "std_ms": 0.0},
                                             "total": {"mean_ms": ms, "std_ms": 0.0}}}

    return BenchResult.from_json({"models": [row(names[0], dense_ms), row(names[1], sparse_ms)]})


def test_each_ratio_is_the_median_with_its_min_max_over_the_runs():
    rep = repeated([_result(100.0, 10.0), _result(120.0, 10.0), _result(110.0, 11.0)])
    total = rep.ratios["dense / sparse"]["total"]
    assert total.values == (10.0, 12.0, 10.0) and total.median == 10.0
    assert total.to_json() == {"median": 10.0, "min": 10.0, "max": 12.0, "values": [10.0, 12.0, 10.0]}
    assert rep.totals["dense"].median == 110.0 and rep.runs == 3 and rep.headline == {}
    assert Repeated.from_json(json.loads(json.dumps(rep.to_json()))) == rep
    text = format_repeated(rep)
    assert "Over 3 runs, each in a process of its own: median [min-max]" in text
    assert "dense / sparse: backbone 10.00x [10.00-12.00], total 10.00x [10.00-12.00]" in text
    assert Spread((1.0, 3.0)).median == 2.0
    with pytest.raises(InputError, match="different rows"):
        repeated([_result(100.0, 10.0), _result(100.0, 10.0, names=("dense", "other"))])


def test_a_run_is_the_same_command_with_its_own_json_file():
    from detector.commands.bench import bench

    ctx = bench.make_context("bench", ["--config", "a.yaml", "--config", "b.yaml", "--data", "ds", "--runs", "3",
                                       "--json", "--threads", "2", "--json-out", "x.json"])
    args = child_args(ctx.params, bench.params, "run0.json")
    assert args[:4] == ["--config", "a.yaml", "--config", "b.yaml"] and "--threads" in args
    assert args[-5:] == ["--runs", "1", "--no-progress", "--json-out", "run0.json"]
    assert "--json" not in args and "x.json" not in args and "--peer" not in args


def test_bench_runs_two_processes_and_reports_their_spread(tmp_path):
    data = make_tiny_dataset(tmp_path / "ds", n_frames=2)
    out = tmp_path / "bench.json"
    res = click.testing.CliRunner().invoke(cli, [
        "bench", "--config", DENSE, "--config", SPARSE, "--data", str(data), "--frames", "1", "--trials", "1",
        "--warmup", "0", "--threads", "1", "--runs", "2", "--json-out", str(out)])
    assert res.exit_code == 0, res.output
    written = json.loads(out.read_text())
    rep = Repeated.from_json(written["repeated"])
    assert rep.runs == 2 and set(rep.ratios) == {"dense / sparse"} and set(rep.totals) == {"dense", "sparse"}
    for comps in rep.ratios.values():
        for s in comps.values():
            assert len(s.values) == 2 and min(s.values) <= s.median <= max(s.values)
    # the tables are the first run's: its row totals are the first values of the spread
    first = BenchResult.from_json(written)
    assert [m.components["total"].mean_ms for m in first.models] == [rep.totals[n].values[0]
                                                                     for n in ("dense", "sparse")]
    assert "Over 2 runs, each in a process of its own" in res.stdout
    res = click.testing.CliRunner().invoke(cli, [
        "bench", "--config", DENSE, "--data", str(data), "--runs", "2", "--rate", "1"])
    assert res.exit_code != 0
