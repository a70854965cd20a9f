"""``detector bench --runtime / --precision``: one row per model x runtime x precision with its JSON fields, the
precisions a CPU cannot compute natively skipped with a note, the headline; ``--rate`` (the CPU budget): the
fixed-rate schedule's arithmetic on a simulated clock and the fields of a real run."""

from __future__ import annotations

import dataclasses
import json

import pytest
from helpers_detector import detector_cli as _cli
from helpers_detector import make_tiny_dataset, write_test_config

from detector.bench.budget import fixed_rate
from detector.bench.report import format_table, headline_line, ratio_rows
from detector.bench.result import BenchResult, ModelResult, Stat
from detector.bench.run import headline_record
from detector.bench.timing import COMPONENTS
from detector.deploy.cpu import cpu_flags, precision_flags, skip_reason

pytest.importorskip("onnxruntime")
pytest.importorskip("openvino")


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    base = tmp_path_factory.mktemp("deploy_bench")
    data = make_tiny_dataset(base / "ds", n_frames=3)
    cfgs = {b: write_test_config(base / f"{b}.yaml", model=dict(backbone=b, head=h))
            for b, h in (("dense", "dense"), ("sparse", "sparse_exact"))}
    return data, cfgs



def test_every_model_runtime_precision_is_a_row_interleaved(setup, tmp_path, capsys):
    data, cfgs = setup
    out = tmp_path / "bench.json"
    code, stdout, _ = _cli(["bench", "--config", cfgs["dense"], "--config", cfgs["sparse"], "--data", data,
                            "--frames", "2", "--trials", "1", "--warmup", "1", "--threads", "1",
                            "--runtime", "torch", "--runtime", "onnxruntime", "--runtime", "openvino",
                            "--precision", "fp32", "--precision", "bf16", "--precision", "int8",
                            "--calibration-split", "test", "--calibration-frames", "2", "--json-out", out], capsys)
    assert code == 0
    result = json.loads(out.read_text())
    rows = {(m["name"].split(" ")[0], m["runtime"], m["precision"]) for m in result["models"]}
    skipped = {(s["name"], s["runtime"], s["precision"]) for s in result["skipped"]}
    flags = cpu_flags()
    for model in ("dense", "sparse+sparse_head"):
        for runtime in ("torch", "onnxruntime", "openvino"):
            for precision in ("fp32", "bf16", "int8"):
                why = skip_reason(runtime, precision, flags)
                key = (model, runtime, precision)
                # each combination is exactly one of: a timed row, a skip with its reason
                assert (key in rows) == (why is None) and (key in skipped) == (why is not None), key
    assert ("dense", "torch", "fp32") in rows and ("dense", "onnxruntime", "fp32") in rows
    assert ("dense", "onnxruntime", "bf16") in skipped and ("dense", "torch", "int8") in skipped
    for m in result["models"]:
        assert set(m["components"]) == set(COMPONENTS)
        assert all(v["mean_ms"] > 0 for v in m["components"].values()), m["name"]
        parts = sum(m["components"][k]["mean_ms"] for k in COMPONENTS[:-1])
        assert m["components"]["total"]["mean_ms"] == pytest.approx(parts, rel=1e-9)
        assert m["back_to_back"] is not None  # deployed rows take part in the back-to-back table too
    names = [m["name"] for m in result["models"]]
    assert names[0] == "dense" and "sparse+sparse_head (onnxruntime fp32)" in names
    assert result["protocol"]["runtimes"] == ["torch", "onnxruntime", "openvino"]
    assert result["protocol"]["calibration"] == {"split": "test", "frames": 2}
    mach = result["machine"]
    assert mach["precision_flags"] == precision_flags(flags) and mach["onnxruntime"] and mach["openvino"]
    # ratio rows stay within one runtime x precision; the headline spans them
    typed = BenchResult.from_json(result)
    assert ("dense / sparse+sparse_head", ) == tuple(n for n, _ in ratio_rows(typed) if "(" not in n)
    assert "dense (onnxruntime fp32) / sparse+sparse_head (onnxruntime fp32)" in [n for n, _ in ratio_rows(typed)]
    assert json.dumps(typed.to_json(), indent=2) + "\n" == out.read_text()  # the one definition reads what it wrote
    h = result["headline"]
    ours = result["models"]
    dense_best = min((m for m in ours if m["backbone"] == "dense"), key=lambda m: m["components"]["total"]["mean_ms"])
    assert h["fastest_dense"] == dense_best["name"]
    assert h["speedup"] == pytest.approx(h["dense_total_ms"] / h["sparse_total_ms"])
    assert "headline: fastest sparse" in stdout and "skipped dense (onnxruntime bf16)" in stdout


def test_skip_reasons_follow_the_cpu_flags():
    avx2 = frozenset({"avx2", "fma"})
    amx = frozenset({"avx2", "avx512f", "amx_bf16", "amx_int8"})
    zen4 = frozenset({"avx2", "avx512f", "avx512_bf16", "avx512_vnni"})
    for flags in (avx2, amx, zen4):
        assert skip_reason("openvino", "fp32", flags) is None and skip_reason("onnxruntime", "fp32", flags) is None
        assert "bf16 kernels" in skip_reason("onnxruntime", "bf16", flags)
        assert "no int8 path" in skip_reason("torch", "int8", flags)
    # the paper's robot CPU (AVX2): no native bf16 or int8, so fp32 is the fair row
    assert "avx512_bf16" in skip_reason("openvino", "bf16", avx2)
    assert "vnni" in skip_reason("onnxruntime", "int8", avx2)
    for flags in (amx, zen4):
        assert skip_reason("openvino", "bf16", flags) is None and skip_reason("openvino", "int8", flags) is None
    assert precision_flags(avx2) == {"bf16": [], "int8": []}
    assert precision_flags(amx) == {"bf16": ["amx_bf16"], "int8": ["amx_int8"]}
    with pytest.raises(ValueError):
        skip_reason("tensorrt", "fp32", avx2)


def test_cpu_flags_read_the_first_flags_line(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nmodel name\t: X\nflags\t\t: fpu avx2 avx512_bf16\n\n"
                    "processor\t: 1\nflags\t: fpu\n")
    assert cpu_flags(info) == {"fpu", "avx2", "avx512_bf16"}
    assert cpu_flags(tmp_path / "missing") == frozenset()


def test_only_skipped_combinations_is_one_error_line(setup, tmp_path, capsys):
    data, cfgs = setup
    code, _, err = _cli(["bench", "--config", cfgs["dense"], "--data", data, "--frames", "1", "--trials", "1",
                         "--runtime", "onnxruntime", "--precision", "bf16", "--json-out", tmp_path / "b.json"], capsys)
    assert code == 2 and err.count("\n") == 1 and "no bf16 kernels" in err
    assert not (tmp_path / "b.json").exists()


def _result(rows: list[tuple[str, str, str, str, float]]) -> BenchResult:
    """A bench result holding only what the headline reads: (name, backbone, runtime, precision, total ms)."""
    return BenchResult(models=tuple(ModelResult(name=n, backbone=b, runtime=r, precision=p,
                                                components={"total": Stat(t, 0.0)}) for n, b, r, p, t in rows))


def test_the_headline_compares_the_fastest_rows_of_each_kind():
    res = _result([("dense", "dense", "torch", "fp32", 450.0), ("dense (openvino fp32)", "dense", "openvino", "fp32",
                                                                 440.0),
                   ("dense (openvino bf16)", "dense", "openvino", "bf16", 90.0),
                   ("sparse", "sparse", "torch", "fp32", 45.0), ("sparse (openvino int8)", "sparse", "openvino",
                                                                 "int8", 15.0)])
    h = headline_record(res.models)
    assert (h.fastest_dense, h.fastest_sparse, h.fastest_fp32_dense) == (
        "dense (openvino bf16)", "sparse (openvino int8)", "dense (openvino fp32)")
    assert h.speedup == pytest.approx(6.0) and h.speedup_vs_fp32_dense == pytest.approx(440 / 15)
    line = headline_line(dataclasses.replace(res, headline=h))
    assert "6.00x" in line and "29.33x" in line
    # eager fp32 only (the tables as before runtimes existed): no headline line; one kind only: no headline
    eager = _result([("dense", "dense", "torch", "fp32", 450.0), ("sparse", "sparse", "torch", "fp32", 45.0)])
    assert headline_line(dataclasses.replace(eager, headline=headline_record(eager.models))) is None
    assert headline_record(_result([("dense", "dense", "torch", "fp32", 1.0)]).models) is None


def test_the_headline_picks_only_rows_within_one_ap_point_of_their_eager_fp32():
    """Given the rows' 3D AP, a row more than 1.0 from its own model's eager fp32 row (the name without its runtime /
    precision suffix) is no side's fastest and is named with why; a row without AP is picked on speed; the headline
    written to JSON and read back keeps the exclusions, and one without any keeps the keys it always had."""
    res = _result([("dense", "dense", "torch", "fp32", 450.0), ("dense (openvino fp32)", "dense", "openvino", "fp32",
                                                                 440.0),
                   ("dense (openvino bf16)", "dense", "openvino", "bf16", 150.0),
                   ("dense (openvino int8)", "dense", "openvino", "int8", 90.0),
                   ("sparse", "sparse", "torch", "fp32", 45.0),
                   ("sparse (openvino int8)", "sparse", "openvino", "int8", 15.0),
                   ("sparse (openvino bf16)", "sparse", "openvino", "bf16", 20.0)])
    ap = {"dense": 50.0, "dense (openvino fp32)": 50.0, "dense (openvino bf16)": 49.2, "dense (openvino int8)": 48.5,
          "sparse": 47.0, "sparse (openvino int8)": 48.01}
    h = headline_record(res.models, ap)
    assert (h.fastest_dense, h.fastest_sparse, h.fastest_fp32_dense) == (
        "dense (openvino bf16)", "sparse (openvino bf16)", "dense (openvino fp32)")
    assert h.speedup == pytest.approx(150 / 20) and h.speedup_vs_fp32_dense == pytest.approx(440 / 20)
    assert h.excluded == ("dense (openvino int8): 3D AP 48.50 is -1.50 from its eager fp32 50.00 (more than 1 3D AP)",
                          "sparse (openvino int8): 3D AP 48.01 is +1.01 from its eager fp32 47.00 (more than 1 3D AP)")
    line = headline_line(dataclasses.replace(res, headline=h))
    assert line.endswith("; left out of the picks (AP guard): " + "; ".join(h.excluded))
    assert type(h).from_json(json.loads(json.dumps(h.to_json()))) == h
    # without AP (a bench alone) the same rows are picked on speed, as before, and the JSON has no "excluded" key
    plain = headline_record(res.models)
    assert (plain.fastest_dense, plain.fastest_sparse, plain.excluded) == (
        "dense (openvino int8)", "sparse (openvino int8)", ())
    assert "excluded" not in plain.to_json() and type(plain).from_json(plain.to_json()) == plain


class SimClock:
    """A simulated clock: ``run`` takes ``costs[i]`` seconds of wall and of CPU, ``sleep`` advances wall only."""

    def __init__(self, costs: list[float]) -> None:
        self.t, self.cpu, self.costs, self.calls = 0.0, 0.0, costs, 0

    def run(self, _frame) -> None:
        c = self.costs[self.calls % len(self.costs)]
        self.calls += 1
        self.t += c
        self.cpu += c

    def sleep(self, dt: float) -> None:
        assert dt >= 0
        self.t += dt


def test_fixed_rate_schedule_counts_misses_drops_and_the_cpu_share():
    # 10 Hz for 1 s: 10 frames. Each takes 30 ms: all on time, 30 % of one core, 7.5 % of four
    sim = SimClock([0.03])
    r = fixed_rate(sim.run, [None], 10.0, 1.0, 4, clock=lambda: sim.t, cpu_clock=lambda: sim.cpu, sleep=sim.sleep)
    assert (r["released"], r["processed"], r["dropped"], r["deadline_misses"]) == (10, 10, 0, 0)
    assert r["wall_s"] == pytest.approx(1.0) and r["cpu_share"] == pytest.approx(0.075)
    assert r["latency_ms"]["p50"] == pytest.approx(30.0) and r["cpu_ms_per_frame"] == pytest.approx(30.0)
    # 25 % of 4 cores at 30 ms a frame: 33.3 Hz, below 1 / service time
    assert r["max_rate_hz_at_25pct"] == pytest.approx(0.25 * 4 / 0.03)

    # 250 ms frames at 10 Hz: every frame is late, and the detector skips to the newest released frame
    sim = SimClock([0.25])
    r = fixed_rate(sim.run, [None], 10.0, 1.0, 1, clock=lambda: sim.t, cpu_clock=lambda: sim.cpu, sleep=sim.sleep)
    # frames 0, 2, 5, 7 start at 0, 0.25, 0.5, 0.75 s: each the newest released when the one before ended
    assert r["processed"] == 4 and r["dropped"] == 6 and r["deadline_misses"] == 4
    assert r["wall_s"] == pytest.approx(1.0) and r["cpu_share"] == pytest.approx(1.0)
    assert r["latency_ms"]["p95"] > r["service_ms"]["p95"] == pytest.approx(250.0)
    # a quarter of one core at 250 ms a frame: 1 Hz
    assert r["max_rate_hz_at_25pct"] == pytest.approx(1.0)


def test_rate_mode_reports_the_budget_of_each_row(setup, tmp_path, capsys):
    data, cfgs = setup
    out = tmp_path / "budget.json"
    code, stdout, _ = _cli(["bench", "--config", cfgs["sparse"], "--data", data, "--frames", "2", "--warmup", "1",
                            "--threads", "1", "--runtime", "torch", "--runtime", "onnxruntime", "--precision", "fp32",
                            "--precision", "bf16", "--rate", "4", "--duration", "1", "--json-out", out], capsys)
    assert code == 0
    result = json.loads(out.read_text())
    flags = cpu_flags()
    combos = [(r, p) for r in ("torch", "onnxruntime") for p in ("fp32", "bf16")]
    assert [(b["runtime"], b["precision"]) for b in result["budget"]] == [
        c for c in combos if skip_reason(*c, flags) is None]
    assert {(s["runtime"], s["precision"]) for s in result["skipped"]} == {
        c for c in combos if skip_reason(*c, flags) is not None}
    assert ("onnxruntime", "bf16") in {(s["runtime"], s["precision"]) for s in result["skipped"]}
    for b in result["budget"]:
        assert b["released"] == 4 and b["processed"] + b["dropped"] == 4 and 0 <= b["deadline_misses"] <= 4
        assert 0 < b["cpu_share"] and b["wall_s"] >= 1.0 and b["threads"] == 1
        assert 0 < b["latency_ms"]["p50"] <= b["latency_ms"]["p95"]
        assert b["service_ms"]["p50"] <= b["latency_ms"]["p50"] + 1e-9
        assert b["peak_rss_mb"] > 10 and b["max_rate_hz_at_25pct"] > 0
    assert result["protocol"]["rate_hz"] == 4 and result["protocol"]["duration_s"] == 1
    assert "CPU share" in stdout and "max Hz at 25 % CPU" in stdout
    code, _, err = _cli(["bench", "--config", cfgs["sparse"], "--data", data, "--rate", "0"], capsys)
    assert code == 2 and err.count("\n") == 1 and "'--rate': '0' must be a finite number from 1e-06" in err


def test_format_table_keeps_eager_only_results_as_before(setup, tmp_path, capsys):
    data, cfgs = setup
    out = tmp_path / "b.json"
    code, stdout, _ = _cli(["bench", "--config", cfgs["dense"], "--config", cfgs["sparse"], "--data", data,
                            "--frames", "1", "--trials", "1", "--warmup", "0", "--threads", "1", "--json-out", out],
                           capsys)
    assert code == 0
    result = json.loads(out.read_text())
    assert [(m["runtime"], m["precision"]) for m in result["models"]] == [("torch", "fp32")] * 2
    assert result["skipped"] == [] and "headline" not in format_table(BenchResult.from_json(result))
