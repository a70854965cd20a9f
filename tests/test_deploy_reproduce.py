"""The reproduction's ``deploy`` step: the commands it runs (dry run) and the report's AP-drop-vs-speed table read back
from what those commands really write (a tiny run)."""

from __future__ import annotations

import json
import statistics
from pathlib import Path

import pytest
from helpers_detector import make_tiny_dataset, write_test_config

from detector.bench.repeat import repeated
from detector.bench.result import BenchDensity, BenchMachine, BenchResult, DensityGrid, ModelResult, Stat
from detector.cli import main as detector_main
from detector.deploy.cpu import cpu_flags, skip_reason
from detector.device import Machine
from reproduction.cli import main
from reproduction.deploy import VARIANTS, deploy_section, deployed_variants, eval_dir, like_for_like, read_deploy

pytest.importorskip("onnxruntime")
pytest.importorskip("openvino")


def test_deploy_step_commands(tmp_path: Path, capsys) -> None:
    out = tmp_path / "w"
    assert main(["--dry-run", "--scale", "small", "--steps", "deploy", "--out", str(out)]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("$ ")]
    evals = [ln for ln in lines if " eval " in ln]
    benches = [ln for ln in lines if " bench " in ln]
    variants = deployed_variants()
    deployed = [(r, p) for r, p in variants if (r, p) != ("torch", "fp32")]  # eager bf16 is evaluated too
    assert variants == [v for v in VARIANTS if skip_reason(*v, cpu_flags()) is None]
    # dense and sparse, every runtime x precision but eager fp32 (the eval step's); the exact head every one
    assert len(evals) == 2 * len(deployed) + len(variants)
    assert ("torch", "bf16") in deployed or skip_reason("torch", "bf16", cpu_flags()) is not None
    for (r, p), ln in zip(deployed * 2 + variants, evals):
        assert f"--runtime {r} --precision {p}" in ln and "--split val" in ln and f"_{r}_{p}" in ln
    n = len(deployed)
    assert "mpchair_dense_cpu.yaml" in evals[0] and "mpchair_sparse_cpu.yaml" in evals[2 * n - 1]
    for ln in evals[2 * n:]:  # the exact sparse head: the sparse model's weights, its own folders
        assert "mpchair_sparse_exact_cpu.yaml" in ln and "runs/sparse/last.pt" in ln and "/sparse_exact_" in ln
    assert len(benches) == 2 and "--rate" not in benches[0] and "--rate 1.0 --duration 5.0" in benches[1]
    for ln in benches:
        assert ln.startswith("$ MALLOC_MMAP_MAX_=0") and "mpchair_sparse_exact.yaml" in ln
        assert "--runtime onnxruntime" in ln and "--runtime openvino" in ln and "--precision fp32" in ln


def _detector(capsys, *args, stdout: Path | None = None) -> None:
    with pytest.raises(SystemExit) as e:
        detector_main([str(a) for a in args])
    captured = capsys.readouterr()
    assert e.value.code == 0, captured.err
    if stdout is not None:
        stdout.write_text(captured.out)


def test_the_report_table_reads_the_step_outputs(tmp_path: Path, capsys) -> None:
    res = tmp_path / "results"
    res.mkdir()
    data = make_tiny_dataset(tmp_path / "ds", n_frames=2, seed=3)
    cfg = write_test_config(tmp_path / "dense.yaml", model=dict(score_thr=0.0))
    from detector.checkpoint import Checkpoint, save_checkpoint
    from detector.config import load_experiment
    from detector.models import build_model

    ckpt = tmp_path / "w.pt"
    save_checkpoint(ckpt, Checkpoint(model=build_model(load_experiment(cfg).model).state_dict()))
    common = ["--config", cfg, "--data", data, "--checkpoint", ckpt, "--split", "val", "--threads", "1"]
    _detector(capsys, "eval", *common, "--out", res / "eval_dense")
    _detector(capsys, "eval", *common, "--out", eval_dir(res, "dense", "onnxruntime", "fp32"), "--runtime",
              "onnxruntime")
    bench = ["--config", cfg, "--data", data, "--split", "val", "--checkpoint", ckpt, "--threads", "1", "--frames",
             "1", "--runtime", "torch", "--runtime", "onnxruntime", "--markdown"]
    _detector(capsys, "bench", *bench, "--trials", "1", "--warmup", "0", "--json-out", res / "deploy_bench.json",
              stdout=res / "deploy_bench.md")
    _detector(capsys, "bench", *bench, "--rate", "2", "--duration", "1", "--warmup", "0", "--json-out",
              res / "deploy_budget.json", stdout=res / "deploy_budget.md")

    rows = {(r.model, r.runtime, r.precision): r for r in read_deploy(res)}
    assert set(rows) == {("dense", "torch", "fp32"), ("dense", "onnxruntime", "fp32")}
    bench_json = json.loads((res / "deploy_bench.json").read_text())
    budget_json = json.loads((res / "deploy_budget.json").read_text())
    ort = rows[("dense", "onnxruntime", "fp32")]
    assert ort.total_ms == bench_json["models"][1]["components"]["total"]["mean_ms"]
    assert ort.cpu_share == budget_json["budget"][1]["cpu_share"]
    eager_ap = json.loads((res / "eval_dense" / "metrics.json").read_text())["Chair"]["3d"]["overall"]["R40"]
    assert ort.metrics.ap["3d"].overall["R40"] == pytest.approx(eager_ap)
    # fp32 deployed finds the same boxes (random weights, score threshold 0: every frame has some)
    ort_dir = eval_dir(res, "dense", "onnxruntime", "fp32") / "data"
    for f in sorted((res / "eval_dense" / "data").glob("*.txt")):
        assert f.read_text().count("\n") == (ort_dir / f.name).read_text().count("\n") > 0
    text = "\n".join(deploy_section(res))
    table = [ln for ln in text.splitlines() if ln.startswith(("| dense | torch |", "| dense | onnxruntime |"))]
    assert len(table) == 2 and "| onnxruntime | fp32 |" in table[1] and "+0.00" in table[1]
    assert f"{eager_ap:.2f}" in table[0] and "1.00x" in table[0]
    assert "### CPU budget at 1 Hz" in text and "CPU share" in text
    assert "not run" in "\n".join(deploy_section(tmp_path / "empty"))


def test_eager_bf16_is_evaluated_and_its_row_reads_its_own_metrics(tmp_path: Path, capsys) -> None:
    """`detector eval --precision bf16` (eager torch) runs the model under bf16 autocast, and the deploy table's eager
    bf16 row takes that evaluation's AP, not the fp32 one's (a table row must be its own measurement)."""
    if skip_reason("torch", "bf16", cpu_flags()) is not None:
        pytest.skip("this CPU has no native bf16")
    res = tmp_path / "results"
    data = make_tiny_dataset(tmp_path / "ds", n_frames=2, seed=3)
    cfg = write_test_config(tmp_path / "dense.yaml", model=dict(score_thr=0.0))
    from detector.checkpoint import Checkpoint, save_checkpoint
    from detector.config import load_experiment
    from detector.models import build_model

    ckpt = tmp_path / "w.pt"
    save_checkpoint(ckpt, Checkpoint(model=build_model(load_experiment(cfg).model).state_dict()))
    common = ["--config", cfg, "--data", data, "--checkpoint", ckpt, "--split", "val", "--threads", "1"]
    _detector(capsys, "eval", *common, "--out", res / "eval_dense")
    bf16_dir = eval_dir(res, "dense", "torch", "bf16")
    _detector(capsys, "eval", *common, "--out", bf16_dir, "--precision", "bf16")
    fp32_files = sorted((res / "eval_dense" / "data").glob("*.txt"))
    bf16_text = [(bf16_dir / "data" / f.name).read_text() for f in fp32_files]
    assert all(t.count("\n") > 0 for t in bf16_text)  # random weights, threshold 0: boxes in every frame
    assert bf16_text != [f.read_text() for f in fp32_files]  # bf16 scores differ in their last digits
    # the table row of a bf16 eval that was not run has no AP (it is not the fp32 one)
    bench = {"models": [{"name": "dense (torch bf16)", "runtime": "torch", "precision": "bf16",
                         "components": {"total": {"mean_ms": 1.0}}}]}
    (res / "deploy_bench.json").write_text(json.dumps(bench))
    (row,) = read_deploy(res)
    assert row.metrics is not None
    assert row.metrics.ap["3d"].overall["R40"] == pytest.approx(
        json.loads((bf16_dir / "metrics.json").read_text())["Chair"]["3d"]["overall"]["R40"])
    import shutil

    shutil.rmtree(bf16_dir)
    (row,) = read_deploy(res)
    assert row.metrics is None


def test_the_exact_heads_rows_read_their_own_evaluations(tmp_path: Path) -> None:
    """The sparse+sparse_head rows (the deployed headline's fastest sparse row is one) take the AP of the exact head's
    own evaluation in that runtime / precision, and their drop is against the exact head's eager fp32 evaluation."""
    res = tmp_path / "results"

    def metrics(folder: Path, ap3d: float) -> None:
        folder.mkdir(parents=True)
        block = {"overall": {"R40": ap3d}}
        (folder / "metrics.json").write_text(json.dumps({"Chair": {"3d": block, "bev": block}}))

    metrics(res / "eval_sparse", 50.0)
    metrics(eval_dir(res, "sparse_exact", "torch", "fp32"), 50.0)
    metrics(eval_dir(res, "sparse_exact", "onnxruntime", "int8"), 49.25)
    models = [{"name": f"sparse+sparse_head{s}", "runtime": r, "precision": p, "components": {"total": {"mean_ms": ms}}}
              for s, r, p, ms in (("", "torch", "fp32", 20.0), (" (onnxruntime int8)", "onnxruntime", "int8", 10.0),
                                  (" (openvino int8)", "openvino", "int8", 12.0))]
    (res / "deploy_bench.json").write_text(json.dumps({"models": models}))
    rows = {(r.runtime, r.precision): r for r in read_deploy(res)}
    assert rows[("onnxruntime", "int8")].metrics.ap["3d"].overall["R40"] == 49.25
    assert rows[("openvino", "int8")].metrics is None  # not evaluated: no AP, not the fp32 one's
    table = [ln for ln in deploy_section(res) if ln.startswith("| sparse+sparse_head |")]
    assert "| 49.25 | -0.75 |" in table[1] and "| – | – |" in table[2]


def test_like_for_like_pairs_the_fastest_of_each_side_at_fp32_and_at_any_precision(tmp_path: Path) -> None:
    res = tmp_path / "results"
    res.mkdir()
    rows = (("dense", "torch", "fp32", 470.0), ("dense (openvino fp32)", "openvino", "fp32", 409.0),
            ("dense (openvino int8)", "openvino", "int8", 86.0), ("sparse", "torch", "fp32", 40.0),
            ("sparse+sparse_head (onnxruntime fp32)", "onnxruntime", "fp32", 19.5),
            ("sparse+sparse_head (onnxruntime int8)", "onnxruntime", "int8", 13.9))
    models = tuple(ModelResult(name=n, runtime=r, precision=p, components={"total": Stat(ms, 0.0)})
                   for n, r, p, ms in rows)
    mach = BenchMachine(Machine(cpu="AMD EPYC", logical_cpus=2, torch_threads=2, torch="2.13"),
                        precision_flags={"bf16": ("avx512_bf16",), "int8": ("avx512_vnni",)}, gemm="onednn")
    density = BenchDensity(frames=3, median=0.0079, mean=0.008, min=0.007, max=0.009,
                           geometry=DensityGrid((0.0, -12.8, -2.0, 38.4, 12.8, 2.0), (0.05, 0.05, 4.0), (512, 768)))
    bench = BenchResult(models=models, machine=mach, density=density)
    (res / "deploy_bench.json").write_text(json.dumps(bench.to_json(), indent=2) + "\n")
    assert like_for_like(tmp_path / "none") == []
    table = like_for_like(res)
    fp32, anyp = table[2], table[3]
    assert "dense, openvino fp32: 409.0 ms" in fp32 and "sparse+sparse_head, onnxruntime fp32: 19.5 ms" in fp32
    assert fp32.endswith(f"| {409.0 / 19.5:.2f}x |")
    assert "dense, openvino int8: 86.0 ms" in anyp and "onnxruntime int8: 13.9 ms" in anyp
    assert anyp.endswith(f"| {86.0 / 13.9:.2f}x |")
    # the paper's architecture (the sparse model with its dense head) at fp32 and at any precision; no deployed row
    assert [ln.split(" | ")[0] for ln in table[4:6]] == ["| the paper's architecture (sparse backbone + dense head), "
                                                         "fp32", "| the paper's architecture, any precision"]
    assert "sparse, torch fp32: 40.0 ms" in table[5] and table[5].endswith(f"| {86.0 / 40.0:.2f}x |")
    note = table[7]
    assert "AMD EPYC, 2 threads of 2 CPUs, allocator reuse" in note and "D median 0.00790" in note
    assert "avx512_bf16, avx512_vnni" in note
    assert table[-1] == (f"Headline: the sparse model with the exact sparse head, our addition to the paper's "
                         f"architecture, at its fastest (onnxruntime int8, 13.9 ms), is {86.0 / 13.9:.2f}x faster than "
                         "the fastest dense deployment (openvino int8, 86.0 ms) on 2 threads of the AMD EPYC above. "
                         f"The paper's architecture (sparse backbone + dense head) against the same dense row: "
                         f"{86.0 / 40.0:.2f}x at its fastest (torch fp32, 40.0 ms). Against the fastest fp32 dense row "
                         f"(openvino fp32, 409.0 ms) the same sparse row is {409.0 / 13.9:.2f}x, but that sets sparse "
                         f"int8 against dense fp32; fp32 on both sides it is {409.0 / 19.5:.2f}x (the first row).")
    assert "### Like for like" in "\n".join(deploy_section(res))


def test_like_for_like_picks_only_rows_within_one_ap_point_of_eager_fp32_and_names_the_rest(tmp_path: Path) -> None:
    """The AP guard on constructed rows, through the real readers (bench JSON + metrics.json files): the fastest dense
    row (OpenVINO int8, 2.3 3D AP below its eager fp32) and the two fastest sparse ones (the exact head's ONNX Runtime
    int8, 1.2 above; its OpenVINO bf16, 1.1 below) are left out and named with their AP; the next fastest within 1.0
    are picked (dense OpenVINO bf16 at -0.9); a row with no evaluation is picked on speed alone and said to be."""
    res = tmp_path / "results"

    def metrics(model: str, runtime: str, precision: str, ap3d: float) -> None:
        from reproduction.deploy import metrics_path

        path = metrics_path(res, model, runtime, precision)
        path.parent.mkdir(parents=True, exist_ok=True)
        block = {"overall": {"R40": ap3d}}
        path.write_text(json.dumps({"Chair": {"3d": block, "bev": block}}))

    timed = (("dense", "torch", "fp32", 300.0, 50.0), ("dense", "openvino", "fp32", 260.0, 50.0),
             ("dense", "openvino", "bf16", 140.0, 49.1), ("dense", "openvino", "int8", 99.0, 47.7),
             ("sparse", "torch", "fp32", 23.0, 48.0), ("sparse", "torch", "bf16", 17.0, 48.5),
             ("sparse", "openvino", "int8", 28.0, None),
             ("sparse+sparse_head", "torch", "fp32", 14.0, 48.0),
             ("sparse+sparse_head", "onnxruntime", "fp32", 13.0, 48.0),
             ("sparse+sparse_head", "onnxruntime", "int8", 8.0, 49.2),
             ("sparse+sparse_head", "openvino", "bf16", 11.0, 46.9))
    for model, r, p, _, ap in timed:
        if ap is not None:
            metrics(model, r, p, ap)
    models = tuple(ModelResult(name=m if (r, p) == ("torch", "fp32") else f"{m} ({r} {p})", runtime=r, precision=p,
                               components={"total": Stat(ms, 0.0)}) for m, r, p, ms, _ in timed)
    (res / "deploy_bench.json").write_text(json.dumps(BenchResult(models=models).to_json()))
    table = like_for_like(res)
    rows = {ln.split(" | ")[0].lstrip("| "): ln for ln in table if ln.startswith("| ") and "ms, 3D AP" in ln}
    fp32, anyp = rows[[k for k in rows if k.startswith("fp32")][0]], rows["any precision this CPU computes natively"]
    assert "dense, openvino bf16: 140.0 ms, 3D AP 49.10" in anyp  # int8 (99 ms, -2.30) left out
    assert "sparse+sparse_head, onnxruntime fp32: 13.0 ms" in anyp
    assert anyp.endswith(f"| {140.0 / 13.0:.2f}x |")
    assert "dense, openvino fp32: 260.0 ms" in fp32 and fp32.endswith(f"| {260.0 / 13.0:.2f}x |")
    paper = rows["the paper's architecture, any precision"]
    assert "dense, openvino bf16: 140.0 ms" in paper and "sparse, torch bf16: 17.0 ms" in paper
    deployed = rows["the paper's architecture, deployed (ONNX Runtime / OpenVINO), any precision"]
    assert "sparse, openvino int8: 28.0 ms, 3D AP –" in deployed  # not evaluated: picked on speed alone
    note = next(ln for ln in table if ln.startswith("Both sides"))
    assert ("left out: dense openvino int8 (3D AP 47.70 is -2.30 from its eager fp32 50.00 (more than 1 3D AP)); "
            "sparse+sparse_head onnxruntime int8 (3D AP 49.20 is +1.20 from its eager fp32 48.00 (more than 1 3D AP)); "
            "sparse+sparse_head openvino bf16 (3D AP 46.90 is -1.10") in note
    assert "not evaluated, so picked on speed alone: sparse openvino int8." in note
    assert table[-1].startswith("Headline: the sparse model with the exact sparse head, our addition to the paper's "
                                f"architecture, at its fastest (onnxruntime fp32, 13.0 ms), is {140.0 / 13.0:.2f}x")
    assert f"(sparse backbone + dense head) against the same dense row: {140 / 17:.2f}x" in table[-1]
    assert "sets sparse" not in table[-1]  # fp32 against fp32: no mixed-precision ratio to warn about


def test_a_repeated_deploy_bench_quotes_each_rows_median_and_the_ratios_min_max(tmp_path: Path) -> None:
    """``detector bench --runs 3`` (the first run's result with ``repeated``): the table, its picks and the headline
    take each row's median total over the runs, not the first run's, and show the ratio's min-max over the runs
    beside it; the big table's ms are the medians too. (A one-run JSON reads as before: the tests above.)"""
    res = tmp_path / "results"
    res.mkdir()
    runs = {("dense", "torch", "fp32"): (470.0, 480.0, 460.0),
            ("dense (openvino fp32)", "openvino", "fp32"): (420.0, 409.0, 400.0),
            ("dense (openvino int8)", "openvino", "int8"): (95.0, 86.0, 80.0),
            ("sparse", "torch", "fp32"): (40.0, 41.0, 39.0),
            # fastest fp32 sparse row in the first run (19.0), but not by its median (22.0 > 19.5)
            ("sparse+sparse_head", "torch", "fp32"): (19.0, 22.0, 23.0),
            ("sparse+sparse_head (onnxruntime fp32)", "onnxruntime", "fp32"): (21.0, 19.5, 18.0),
            ("sparse+sparse_head (onnxruntime int8)", "onnxruntime", "int8"): (15.0, 13.9, 12.0)}
    results = [BenchResult(models=tuple(ModelResult(name=n, runtime=r, precision=p,
                                                    components={"total": Stat(ms[i], 0.0)})
                                        for (n, r, p), ms in runs.items())) for i in range(3)]
    (res / "deploy_bench.json").write_text(json.dumps({**results[0].to_json(),
                                                       "repeated": repeated(results).to_json()}))
    med = {n.split(" (")[0] + (f" {r} {p}"): statistics.median(ms) for (n, r, p), ms in runs.items()}
    rows = {f"{r.model} {r.runtime} {r.precision}": r for r in read_deploy(res)}
    assert rows["dense openvino int8"].total_ms == 86.0 and rows["dense openvino int8"].runs == (95.0, 86.0, 80.0)

    def spread(d: str, sp: str) -> str:
        per_run = [a / b for a, b in zip(rows[d].runs, rows[sp].runs)]
        return f"{med[d] / med[sp]:.2f}x (per run {min(per_run):.2f}-{max(per_run):.2f}x)"

    table = like_for_like(res)
    fp32, anyp = table[2], table[3]
    assert "sparse+sparse_head, onnxruntime fp32: 19.5 ms" in fp32 and "dense, openvino fp32: 409.0 ms" in fp32
    assert fp32.endswith(f"| {spread('dense openvino fp32', 'sparse+sparse_head onnxruntime fp32')} |")
    assert "dense, openvino int8: 86.0 ms" in anyp and "sparse+sparse_head, onnxruntime int8: 13.9 ms" in anyp
    headline_ratio = spread("dense openvino int8", "sparse+sparse_head onnxruntime int8")
    assert anyp.endswith(f"| {headline_ratio} |") and headline_ratio == "6.19x (per run 6.19-6.67x)"
    note = next(ln for ln in table if ln.startswith("Both sides"))
    assert "(`detector bench --runtime --precision --runs 3`: 3 such processes one after another; each row's ms is " \
           "its median over the runs" in note
    assert table[-1] == (f"Headline: the sparse model with the exact sparse head, our addition to the paper's "
                         f"architecture, at its fastest (onnxruntime int8, 13.9 ms), is {headline_ratio} faster than "
                         "the fastest dense deployment (openvino int8, 86.0 ms), each ms the row's median over 3 bench "
                         "runs. The paper's architecture (sparse backbone + dense head) against the same dense row: "
                         f"{spread('dense openvino int8', 'sparse torch fp32')} at its fastest (torch fp32, 40.0 ms). "
                         "Against the fastest fp32 dense row (openvino fp32, 409.0 ms) the same sparse row is "
                         f"{spread('dense openvino fp32', 'sparse+sparse_head onnxruntime int8')}, but that sets "
                         "sparse int8 against dense fp32; fp32 on both sides it is "
                         f"{spread('dense openvino fp32', 'sparse+sparse_head onnxruntime fp32')} (the first row).")
    section = deploy_section(res)
    eager = next(ln for ln in section if ln.startswith("| dense | torch | fp32 |"))
    assert "| 470.0 | 1.00x |" in eager
    assert any("(reuse allocator), the median of 3 runs, each a process of its own (`--runs 3`)" in ln
               for ln in section)
