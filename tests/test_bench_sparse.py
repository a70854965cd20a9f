"""``tools/bench_sparse.py`` and its library (``detector.bench.sparse_ratios``, ``detector.bench.timing.time_calls``,
``detector.device.rerun_under``): the timer's protocol, the targets summary, the re-run under new variables, and bad
options failing as one line before any timing. No timing is judged here."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from detector.bench.sparse_ratios import TARGETS, format_summary, summary
from detector.bench.timing import time_calls
from tests.helpers_tools import load_tool


def test_time_calls_warms_up_then_interleaves_every_function() -> None:
    calls: list[str] = []
    out = time_calls({"a": lambda: calls.append("a"), "b": lambda: calls.append("b")}, repeats=3, warmup=2)
    assert calls == ["a", "b"] * 5  # 2 warm-up rounds, then 3 timed rounds, each in turn
    assert set(out) == {"a", "b"}
    for v in out.values():
        assert set(v) == {"min_ms", "median_ms", "cpu_min_ms", "faults"}
        assert 0 <= v["min_ms"] <= v["median_ms"]
        assert v["cpu_min_ms"] >= 0 and v["faults"] >= 0


def _t(wall: float, cpu: float) -> dict[str, float]:
    return {"min_ms": wall, "median_ms": wall, "cpu_min_ms": cpu, "faults": 0}


def test_summary_takes_each_targets_row_and_ratio_of_the_minima() -> None:
    results = {
        "backbone": [
            {"case": "matterport 768x512 clustered 0.75%", "timings": {"dense": _t(300, 600), "sparse": _t(20, 30)}},
            {"case": "kitti 504x440 clustered 2.50%", "timings": {"dense": _t(200, 400), "sparse": _t(100, 100)}},
        ],
        "e2e": [{"case": "matterport", "timings": {"dense": _t(500, 500), "sparse+sparse_exact": _t(100, 50),
                                                   "sparse+dense_head": _t(1, 1)}}],
    }
    rows = summary(results)
    assert [r["target"] for r in rows] == [TARGETS[0][2], TARGETS[1][2], TARGETS[2][2]]  # no train section: no (d)
    assert [(r["wall"], r["cpu"], r["met"]) for r in rows] == [(15.0, 20.0, True), (5.0, 10.0, False),
                                                               (2.0, 4.0, False)]
    text = format_summary(rows, {"threads": 2, "allocator_reuse": True, "omp_wait_policy": "PASSIVE"})
    assert "2 threads, batch 1, allocator reuse, OMP_WAIT_POLICY PASSIVE" in text
    assert text.count("MISSED") == 2 and text.count("  met") == 1


def test_rerun_under_reexecutes_with_the_variables_once(tmp_path) -> None:
    script = tmp_path / "probe.py"
    script.write_text(textwrap.dedent("""
        import os, sys
        from detector.device import rerun_under
        print("start", os.environ.get("BENCH_PROBE", "unset"), sys.argv[1:], flush=True)
        rerun_under({"BENCH_PROBE": "on"}, [__file__, *sys.argv[1:]])
        print("running", os.environ["BENCH_PROBE"], sys.argv[1:])
    """))
    env = {k: v for k, v in os.environ.items() if k != "BENCH_PROBE"}
    out = subprocess.run([sys.executable, str(script), "--x", "1"], capture_output=True, text=True, env=env,
                         check=True).stdout.splitlines()
    assert out == ["start unset ['--x', '1']", "start on ['--x', '1']", "running on ['--x', '1']"]


@pytest.mark.parametrize(("args", "says"), [
    (["--repeats", "0"], "--repeats, --train-repeats and --frames must be >= 1"),
    (["--threads", "0"], "--threads must be >= 1"),
    (["--data", "no/such/dataset"], "no/such/dataset: dataset folder not found"),
])
def test_bad_options_are_one_error_line_before_any_timing(args, says, capsys) -> None:
    tool = load_tool("bench_sparse")
    assert tool.main(args) == 2
    out, err = capsys.readouterr()
    assert out == ""  # not even the header: nothing was timed
    assert err.startswith(f"error: {says}") and err.count("\n") == 1
