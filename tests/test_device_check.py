"""``tools/device_check.sh --dry-run``: the GPU check's every step on the CPU with tiny sizes, so that the script a
lent GPU runs cannot rot unnoticed; plus its time budget, its argument errors and the functions of its Python side
(``reproduction.device_check``)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from detector.bench.result import BenchResult
from detector.bench.timing import TITLES
from reproduction.device_check.cli import main as device_check_main
from reproduction.device_check.jobs import throughput
from reproduction.device_check.report import paper_rows

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tools" / "device_check.sh"
MODELS = ["dense", "sparse", "sparse+sparse_head"]
STEPS = {"tests", "synth", "generate", "bench_mpchair", "bench_kitti", "eval", "ddp",
         *(f"train_{m}_{p}" for m in ("dense", "sparse", "sparse_exact") for p in ("fp32", "autocast"))}


def _run(*args: str, timeout: float = 900) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run(["bash", str(SCRIPT), "--python", sys.executable, *args], env=env, capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT)


@pytest.fixture(scope="module")
def dry_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("device_check") / "out"
    proc = _run("--dry-run", "--out", str(out))
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-5000:]
    assert "device check:" in proc.stdout and f"results in {out}" in proc.stdout
    return out


@pytest.mark.slow
def test_dry_run_writes_every_result(dry_run):
    res = dry_run / "results"
    for name in ["machine.json", "tests.json", "bench_mpchair.json", "bench_mpchair.md", "bench_kitti.json",
                 "bench_kitti.md", "eval.json", "ddp.json"]:
        assert (res / name).is_file(), name
    assert {p.stem for p in (res / "steps").glob("*.json")} == STEPS
    assert len(list((res / "train").glob("*.json"))) == 6
    summary = json.loads((dry_run / "summary.json").read_text())
    assert set(summary) == {"dry_run", "machine", "steps", "tests", "bench", "paper_desktop", "train", "eval", "ddp",
                            "failed"}
    assert summary["dry_run"] is True and summary["failed"] == []
    assert summary["machine"]["device"] == "cpu" and summary["machine"]["autocast_dtype"] == "bfloat16"
    for s in summary["steps"]:
        assert s["status"] == "ok" and s["returncode"] == 0 and s["seconds"] > 0, s
    t = summary["tests"]
    assert t["passed"] >= 2 and t["failed"] == t["errors"] == 0 and t["total"] == len(t["cases"])


@pytest.mark.slow
def test_dry_run_bench_train_eval_ddp_numbers(dry_run):
    summary = json.loads((dry_run / "summary.json").read_text())
    for geometry, split, shape in (("mpchair", "test", [96, 64]), ("kitti", "val", [80, 80])):
        bench = summary["bench"][geometry]
        assert [m["name"] for m in bench["models"]] == MODELS
        assert bench["protocol"]["split"] == split and bench["protocol"]["frames"] == 2
        assert bench["density"]["geometry"]["output_shape"] == shape and bench["machine"]["device"] == "cpu"
        for m in bench["models"]:
            assert all(v["mean_ms"] > 0 for v in m["components"].values()), (geometry, m["name"])
    rows = summary["train"]
    assert [(r["model"], r["precision"]) for r in rows] == [
        (m, p) for m in ("dense", "sparse", "sparse_exact") for p in ("fp32", "autocast")]
    for r in rows:
        assert r["status"] == "ok" and r["steps_done"] == r["steps"] == 3 and r["batch_size"] == 1, r
        assert r["steps_per_s"] > 0 and r["samples_per_s"] == pytest.approx(r["steps_per_s"])
        assert r["peak_memory_mib"] > 50 and math.isfinite(r["last_loss"]) and r["last_loss"] > 0
        assert r.get("autocast_dtype") == ("bf16" if r["precision"] == "autocast" else None)
    ev = summary["eval"]
    assert set(ev["Chair"]) == {"bbox", "bev", "3d", "aos"} and ev["num_gt_overall"]["Chair"] > 0
    ddp = summary["ddp"]
    assert ddp["ran"] and ddp["backend"] == "gloo" and ddp["steps_done"] == 2
    assert all(x > 0 and math.isfinite(x) for x in ddp["loss"]) and all(n > 0 for n in ddp["num_pos"])


@pytest.mark.slow
def test_dry_run_markdown_tables(dry_run):
    md = (dry_run / "summary.md").read_text()
    lines = md.splitlines()
    assert lines[0].startswith("# GPU check") and "--dry-run" in lines[0]
    assert sum(line.startswith("| model | To Device |") for line in lines) == 2  # the two bench tables
    for name in MODELS:
        assert sum(line.startswith(f"| {name} |") for line in lines) >= 4, name  # per frame and back to back, x 2
    # the paper's Desktop numbers beside ours, each of the 7 components in both geometries
    assert sum(line.startswith("| Total | 20.154 ± 0.143 |") for line in lines) == 1
    assert sum(line.startswith("| Total | 14.410 ± 0.033 |") for line in lines) == 1
    assert sum(line.startswith("| Backbone | ") for line in lines) == 2
    for model in ("dense", "sparse", "sparse_exact"):
        assert any(line.startswith(f"| {model} | fp32 | 1 | 1 |") for line in lines), model
        assert any(line.startswith(f"| {model} | bf16 | 1 | 1 |") for line in lines), model
    assert "ok: gloo, world size 2, 2 steps" in md
    assert (dry_run / "results" / "bench_mpchair.md").read_text().startswith("| model | To Device |")


def test_budget_skips_steps_and_the_report_still_runs(tmp_path):
    proc = _run("--dry-run", "--out", str(tmp_path), "--steps", "tests,report", "--budget", "0", timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    (step,) = summary["steps"]
    assert step["name"] == "tests" and step["status"] == "skipped" and "budget" in step["reason"]
    assert summary["tests"] is None and summary["failed"] == []
    assert "| tests | skipped |" in (tmp_path / "summary.md").read_text()


def test_bad_arguments(tmp_path):
    proc = _run("--frobnicate", timeout=60)
    assert proc.returncode == 2 and "unknown argument --frobnicate" in proc.stderr
    assert "--dry-run" in _run("--help", timeout=60).stdout


def test_throughput_skips_warmup_steps():
    steps = [{"time_s": t, "loss_total": 1.0} for t in (9.0, 5.0, 0.5, 0.25, 0.75)]
    got = throughput(steps, batch=6)
    assert got["timed_steps"] == 3 and got["step_s_mean"] == pytest.approx(0.5)
    assert got["steps_per_s"] == pytest.approx(2.0) and got["samples_per_s"] == pytest.approx(12.0)


def test_paper_rows_put_ours_beside_the_desktop_column():
    comps = {k: {"mean_ms": 1.0 + i, "std_ms": 0.0} for i, k in enumerate(TITLES)}
    bench = {"models": [{"name": "dense", "components": comps}, {"name": "sparse", "components": comps},
                        {"name": "open3d-ml", "peer": "open3d-ml", "components": comps}]}
    rows = paper_rows(BenchResult.from_json(bench), "mpchair")
    assert [r[0] for r in rows] == list(TITLES.values())
    assert rows[-1] == ["Total", "20.154 ± 0.143", "7.000", "13.655 ± 0.060", "7.000", "-"]
    assert rows[3][1:3] == ["2.512 ± 0.017", "4.000"]  # Backbone


def test_junit_to_json(tmp_path):
    xml = tmp_path / "t.xml"
    xml.write_text('<testsuites><testsuite><testcase classname="t" name="a[cpu]" time="0.5"/>'
                   '<testcase classname="t" name="a[cuda]" time="0"><skipped message="no CUDA"/></testcase>'
                   '<testcase classname="t" name="b" time="1"><failure message="boom"/></testcase>'
                   '</testsuite></testsuites>')
    assert device_check_main(["tests", "--junit", str(xml), "--out", str(tmp_path / "t.json")]) == 1  # a failure
    got = json.loads((tmp_path / "t.json").read_text())
    assert (got["total"], got["passed"], got["failed"], got["skipped"]) == (3, 1, 1, 1)
    assert got["skip_reasons"] == {"no CUDA": 1} and got["seconds"] == 1.5
    assert got["cases"][2] == {"name": "t::b", "outcome": "failed", "seconds": 1.0, "message": "boom"}


def test_a_step_without_a_command_is_one_error_line(tmp_path, capsys):
    """The Python side's bad input goes through the console scripts' error path: one line, exit 2, nothing written."""
    assert device_check_main(["step", "x", "--results", str(tmp_path)]) == 2
    assert capsys.readouterr().err == "error: step needs a command after --\n"
    assert not (tmp_path / "steps").exists()
