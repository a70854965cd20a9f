"""The report sections issue 30 added to ``make reproduce`` (docs/results.md), each written from its step's JSON and
"not run" without it: the training time (from the runs' metrics.jsonl), the total time with the reference's head
layout (``tools/bench_reference_head.py``), the backbone ratio against density D (``tools/bench_density.py``) and the
ablations (``detector bench`` of the ablation configs, their evals); and the commands of those steps."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import pytest
import torch
from helpers_detector import make_tiny_dataset, write_run_config, write_test_config

from detector.bench.density import crossings
from detector.models import build_model
from detector.models.reference_head import nchw, reference_head
from reproduction.cli import main
from reproduction.report import differences_section, targets_section
from reproduction.report_ablations import ablations_section
from reproduction.report_runtime import density_curve_section, reference_head_section, training_time_section
from reproduction.status import status_lines

ROOT = Path(__file__).resolve().parents[1]


def _figure(src: Path, name: str) -> str:
    return f"img/{name}"


def test_every_new_section_says_not_run_without_its_outputs(tmp_path: Path) -> None:
    assert training_time_section(tmp_path)[2] == "not run"
    assert reference_head_section(tmp_path)[2] == "not run"
    assert density_curve_section(tmp_path, _figure)[2] == "not run"
    text = "\n".join(ablations_section(tmp_path))
    assert "Runtime, KITTI geometry" in text and text.count(": not run") == 3  # both runtimes, the AP
    assert "AP on Matterport-Chair: not run (opt in: `make reproduce-ablations`" in text
    assert "The paper trained and timed its ablations on KITTI Car. There is no KITTI training set here" in text
    assert not [r for r in targets_section(tmp_path) if "reference's head" in r]


def _run(out: Path, model: str, epochs: list[float], steps: list[float], grid=(288, 144), precision="bf16") -> None:
    run = out / "runs" / model
    run.mkdir(parents=True)
    write_run_config(run, model={"output_shape": list(grid)}, train={"epochs": len(epochs), "precision": precision})
    records = [{"kind": "step", "step": i + 1, "epoch": 1, "time_s": t} for i, t in enumerate(steps)]
    records += [{"kind": "epoch", "epoch": i + 1, "time_s": t} for i, t in enumerate(epochs)]
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))


def test_training_time_is_read_from_the_runs_metrics(tmp_path: Path) -> None:
    """Per epoch the median, per step the median, the whole run the sum of the epochs; sparse's speed-up beside the
    paper's 1.8x; an ablation's run gets its own row."""
    _run(tmp_path, "dense", [100.0, 110.0, 90.0, 100.0], [0.5, 0.7, 0.5])
    _run(tmp_path, "sparse", [40.0] * 5, [0.2, 0.2, 0.3])
    _run(tmp_path, "sparse_wide", [70.0, 80.0], [0.4])
    text = "\n".join(training_time_section(tmp_path))
    assert "| dense | 4 | 100.0 | 0.500 | 6.7 |" in text
    assert "| sparse | 5 | 40.0 | 0.200 | 3.3 |" in text
    assert "| sparse_wide | 2 | 75.0 | 0.400 | 2.5 |" in text
    assert ("Sparse / dense: an epoch is 2.50x as fast, the whole run 2.00x with 1.25x the epochs (paper: sparse "
            "trains 1.8x faster despite 25% more epochs") in text
    assert "in bf16 on the 288 x 144 canvas (the paper's 768 x 512 has 9.5x its cells" in text


def test_the_reference_head_computes_the_fused_heads_maps(tmp_path: Path) -> None:
    """Three separate 1x1 convs on the NCHW map give the fused inference head's maps (float64)."""
    cfg = _cfg(tmp_path, "dense").model
    model = build_model(cfg).double().eval()
    x = torch.randn(1, sum(cfg.neck_channels), 8, 6, dtype=torch.float64).contiguous(memory_format=torch.channels_last)
    with torch.no_grad():
        fused = model.anchor_head(x, None)
        ref = reference_head(model.anchor_head, nchw(x))
    assert nchw(x).is_contiguous() and not x.is_contiguous()
    for a, b in zip(fused, ref):
        assert a.shape == b.shape and torch.allclose(a, b, atol=1e-9, rtol=0)


def _cfg(tmp_path: Path, backbone: str):
    from detector.config import load_experiment

    return load_experiment(write_test_config(tmp_path / f"{backbone}.yaml", model=dict(backbone=backbone)))


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> dict[str, Path]:
    """A tiny dataset and slim dense / sparse / Sparse1+Dense23 test configs."""
    root = tmp_path_factory.mktemp("tiny")
    out = {"data": make_tiny_dataset(root / "dataset", n_frames=3, seed=2)}
    for m in ("dense", "sparse", "sparse1_dense23"):
        out[m] = write_test_config(root / f"{m}.yaml", model=dict(backbone=m))
    return out


def _tool(name: str, args: list[str], stdout: Path, capsys) -> None:
    """Run ``tools/<name>.py`` in this process, its stdout to ``stdout`` (as the Runner redirects it)."""
    import importlib

    module = importlib.import_module(f"tools.{name}")
    assert module.main([str(a) for a in args]) == 0
    stdout.write_text(capsys.readouterr().out)


def test_reference_head_section_is_written_from_the_benchs_json(tiny, tmp_path: Path, capsys) -> None:
    res = tmp_path / "results"
    res.mkdir()
    _tool("bench_reference_head", ["--config", tiny["dense"], "--config", tiny["sparse"], "--data", tiny["data"],
                                   "--frames", "2", "--trials", "1", "--warmup", "0", "--threads", "1", "--json-out",
                                   res / "bench_reference_head.json"], res / "bench_reference_head.md", capsys)
    result = json.loads((res / "bench_reference_head.json").read_text())
    ms = {m["name"]: m["mean_ms"] for m in result["models"]}
    for m in ("dense", "sparse"):  # the reference head replaces ours in each frame's total
        assert ms[m]["total_reference_head"] == pytest.approx(ms[m]["total"] - ms[m]["head"] + ms[m]["head_reference"])
    ours = ms["dense"]["total"] / ms["sparse"]["total"]
    ref = ms["dense"]["total_reference_head"] / ms["sparse"]["total_reference_head"]
    text = "\n".join(reference_head_section(res))
    assert (res / "bench_reference_head.md").read_text().strip() in text
    assert (f"Dense / sparse total time: {ours:.2f}x with our head, {ref:.2f}x with the reference's layout (paper, "
            "robot CPU: 1082.135 / 236.737 ms = 4.6x).") in text
    (row,) = [r for r in targets_section(res) if "reference's head layout" in r]
    assert row.endswith(f"| paper 4.6 (robot CPU) | {ref:.1f}x |")
    (head,) = [r for r in differences_section(tmp_path, {}, res) if r.startswith("| head at inference |")]
    assert head.endswith(f"not the paper's 4.6x (with the reference's head layout: {ref:.1f}x, section \"Total time "
                         "with the reference's head layout\") |")


def test_density_crossings_interpolate_in_log_d() -> None:
    d = [0.001, 0.01, 0.1]
    c = crossings(d, [4.0, 2.0, 0.5], [100.0, 10.0, 0.25])
    assert c["ratio_one"] == pytest.approx(math.sqrt(0.01 * 0.1))  # log 2 above and below 1: half-way in log D
    t = math.log(5) / (math.log(5) + math.log(2))
    assert c["meets_ops"] == pytest.approx(0.01 * 10 ** t) and c["ratio_one_extrapolated"] is None
    c = crossings([0.001, 0.01], [8.0, 4.0], [100.0, 10.0])  # halving per decade: 1 three decades further on
    assert c["ratio_one"] is None and c["meets_ops"] is None and c["ratio_one_extrapolated"] == pytest.approx(1.0)


def test_density_curve_section_is_written_from_the_tools_json(tiny, tmp_path: Path, capsys) -> None:
    res = tmp_path / "results"
    res.mkdir()
    (res / "density.json").write_text(json.dumps({"summary": {"median": 0.0061, "min": 0.001, "max": 0.01}}))
    _tool("bench_density", ["--dense-config", tiny["dense"], "--sparse-config", tiny["sparse"], "--densities",
                            "0.01,0.05", "--frames", "1", "--trials", "1", "--warmup", "0", "--threads", "1", "--data",
                            tiny["data"], "--real-frames", "1", "--json-out", res / "density_curve.json", "--plot",
                            res / "density_curve.png", "--mark", "this dataset=0.0061"],
          res / "density_curve.md", capsys)
    curve = json.loads((res / "density_curve.json").read_text())
    assert [p["target_density"] for p in curve["points"]] == [0.01, 0.05] and len(curve["real"]) == 1
    for p in curve["points"]:  # round(D x canvas) clustered sites; ratios of the measured times and of the MACs
        assert p["pillars"] == round(p["target_density"] * 96 * 64) and p["op_ratio"] > 1
        assert p["runtime_ratio"] == pytest.approx(p["dense_ms"] / p["sparse_ms"])
    copied = {}
    text = "\n".join(density_curve_section(res, lambda src, name: copied.setdefault(name, src) and f"img/{name}"))
    assert (res / "density_curve.md").read_text().strip() in text and "real frame 000000" in text
    assert "this run's test split: median D 0.00610" in text and "random (seed 0; timing only)" in text
    assert "![dense / sparse against D](img/density_curve.png)" in text
    assert copied["density_curve.png"].stat().st_size > 1000


def _metrics(kitti: tuple[float, float], o3d: tuple[float, float]) -> tuple[dict, dict]:
    """A metrics.json (BEV, 3D Overall R40) and an open3d_ml.json (BEV, 3D) as detector eval writes them."""
    block = lambda x: {"R40": [x, x, x], "R11": [x, x, x], "overall": {"R40": x, "R11": x}}  # noqa: E731
    return ({"Chair": {"bev": block(kitti[0]), "3d": block(kitti[1])}},
            {"Chair": {"bev": o3d[0], "3d": o3d[1]}})


def test_ablations_section_is_written_from_the_bench_and_eval_outputs(tiny, tmp_path: Path, capsys) -> None:
    """The runtime table of a real ``detector bench`` of dense, sparse and an ablation (random weights), and the AP
    table of their evals: dense absolute, the others as deltas, the paper's KITTI deltas beside."""
    from detector.cli import main as detector_main

    res = tmp_path / "results"
    res.mkdir()
    with pytest.raises(SystemExit) as e:
        detector_main(["bench", "--config", str(tiny["dense"]), "--config", str(tiny["sparse"]), "--config",
                       str(tiny["sparse1_dense23"]), "--data", str(tiny["data"]), "--frames", "1", "--trials", "1",
                       "--warmup", "0", "--threads", "1", "--json-out", str(res / "bench_ablations_kitti.json"),
                       "--no-progress"])
    assert e.value.code == 0
    capsys.readouterr()
    for m, kitti, o3d in (("dense", (60.0, 55.0), (80.0, 81.0)), ("sparse", (57.0, 50.5), (79.0, 78.0)),
                          ("sparse1_dense23", (58.5, 52.0), (80.5, 79.5))):
        (res / f"eval_{m}").mkdir()
        k, o = _metrics(kitti, o3d)
        (res / f"eval_{m}" / "metrics.json").write_text(json.dumps(k))
        (res / f"eval_{m}" / "open3d_ml.json").write_text(json.dumps(o))
    text = "\n".join(ablations_section(res))
    bench = {m["name"]: m["components"] for m in json.loads((res / "bench_ablations_kitti.json").read_text())["models"]}
    s1 = bench["sparse1_dense23"]
    ratio = bench["dense"]["total"]["mean_ms"] / s1["total"]["mean_ms"]
    assert "random weights (timing only), allocator reuse" in text
    assert (f"| Sparse1+Dense23 | {s1['backbone']['mean_ms']:.1f} | {s1['total']['mean_ms']:.1f} | " in text
            and f"| {ratio:.2f}x | 7.394 / 14.602 |" in text and "| 2.358 / 14.410 |" in text)
    assert "Runtime, Matterport geometry (768 x 512, 5 cm pillars; this run's test split): not run" in text
    assert "| PointPillars | 60.00 | 55.00 | 80.00 | 81.00 | 89.79 / 80.34 |" in text
    assert "| Sparse PointPillars | -3.00 | -4.50 | -1.00 | -3.00 | -6.53 / -7.83 |" in text
    assert "| Sparse1+Dense23 | -1.50 | -3.00 | +0.50 | -1.50 | -5.44 / -7.36 |" in text
    assert "| Sparse+WideConv (released code: 9x9 down-conv) | not run | | | | -7.24 / -11.57 |" in text


def test_the_new_steps_commands(tmp_path: Path, capsys) -> None:
    """refhead and curve time at 768 x 512 (trained weights once both exist, the dataset's median D marked on the
    curve); ablation-bench times every ablation at both geometries (KITTI: the vendored frames); the ablations'
    trainings run only when asked for, with the sparse model's epochs or --ablation-epochs."""
    out = tmp_path / "w"
    (out / "results").mkdir(parents=True)
    (out / "results" / "density.json").write_text(json.dumps({"summary": {"median": 0.00612}}))
    assert main(["--dry-run", "--scale", "small", "--out", str(out)]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("$ ")]
    (refhead,) = [ln for ln in lines if "bench_reference_head.py" in ln]
    assert "mpchair_dense.yaml --config" in refhead and "--checkpoint" not in refhead
    assert refhead.startswith("$ MALLOC_MMAP_MAX_=0") and refhead.endswith("bench_reference_head.md")
    (curve,) = [ln for ln in lines if "bench_density.py" in ln]
    assert "--densities 0.002,0.0075,0.0246" in curve and "--mark 'this dataset (median)=0.00612'" in curve
    assert f"--data {out.resolve()}/dataset --split test --real-frames 2" in curve
    benches = [ln for ln in lines if " bench " in ln and "bench_ablations" in ln]
    assert len(benches) == 2 and all(ln.count("--config") == 6 for ln in benches)
    assert f"--data {ROOT}/tests/data/kitti --split val --frames 6" in benches[0]
    assert "kitti_car_sparse_wide_down.yaml" in benches[0] and "mpchair_sparse12_dense3.yaml" in benches[1]
    assert not [ln for ln in lines if " train " in ln and "sparse_wide" in ln]  # opt in only

    assert main(["--dry-run", "--scale", "small", "--out", str(out), "--steps", "ablations", "--ablations",
                 "sparse_wide,sparse1_dense23", "--ablation-epochs", "4"]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("$ ")]
    train = [ln for ln in lines if " train " in ln]
    assert [ln.split("--out ")[1].split()[0].rsplit("/", 1)[1] for ln in train] == ["sparse_wide", "sparse1_dense23"]
    assert all(ln.endswith("--epochs 4") and "_cpu.yaml" in ln for ln in train)
    assert len([ln for ln in lines if " eval " in ln]) == 4
    assert main(["--dry-run", "--scale", "small", "--out", str(out), "--steps", "ablations"]) == 0
    train = [ln for ln in capsys.readouterr().out.splitlines() if " train " in ln and ln.startswith("$ ")]
    assert len(train) == 4 and all(ln.endswith("--epochs 3") for ln in train)  # the small scale's sparse epochs
    assert main(["--dry-run", "--out", str(out), "--ablations", "wider"]) == 2
    assert "--ablations takes a comma-separated subset of" in capsys.readouterr().err
    text = "\n".join(status_lines(out))
    assert "  ablations 0 of 12 outputs" in text and "    sparse_wide: not started" in text


def test_the_tools_refuse_bad_input_in_one_line_and_write_nothing(tiny, tmp_path: Path, capsys) -> None:
    import tools.bench_density as density
    import tools.bench_reference_head as refhead

    out = tmp_path / "r.json"
    cases = [
        (refhead, ["--config", tiny["dense"], "--config", tiny["sparse"], "--checkpoint", "-", "--data", tiny["data"],
                   "--json-out", out], "give one --checkpoint per --config"),
        (refhead, ["--config", tiny["dense"], "--data", tmp_path / "none", "--json-out", out], "none"),
        (density, ["--dense-config", tiny["sparse"], "--sparse-config", tiny["dense"], "--json-out", out],
         "needs a dense config first and a sparse one second"),
        (density, ["--mark", "mine=2", "--json-out", out], "--mark takes LABEL=D with 0 < D < 1, got 'mine=2'"),
        (density, ["--densities", "0.01,x", "--json-out", out], "error: --densities"),
        (density, ["--densities", "0.01,1.5", "--json-out", out], "densities must lie in (0, 1)"),
    ]
    for tool, args, said in cases:
        assert tool.main([str(a) for a in args]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: ") and said in err[0], err
        assert not out.exists()


def test_the_density_curve_names_its_lines_in_a_legend_and_labels_ticks_plainly() -> None:
    """The committed run's curve redrawn: every vertical line (the paper's densities, this dataset's median) is a
    legend entry beside the plot, no text sits at the lines (close densities put their labels on each other), and the
    D axis is labelled in plain decimals (its log-axis minor labels collided)."""
    import matplotlib.pyplot as plt

    from detector.bench.density import PAPER_DENSITY, curve_figure

    result = json.loads((Path(__file__).resolve().parents[1] / "docs" / "results-data" / "results" /
                         "density_curve.json").read_text())
    fig = curve_figure(result, {"this dataset (median)": 0.00788})
    try:
        (ax,) = fig.axes
        legend = [t.get_text() for t in ax.get_legend().get_texts()]
        for label, d in {**PAPER_DENSITY, "this dataset (median)": 0.00788}.items():
            assert f"D = {d:.4f}: {label}" in legend, legend
        assert not ax.texts
        fig.canvas.draw()
        ticks = [t.get_text() for t in ax.get_xticklabels() if t.get_text()]
        assert ticks and all(re.fullmatch(r"0\.\d+", t) for t in ticks), ticks
        assert not [t for t in ax.xaxis.get_minorticklabels() if t.get_text()]
        # the legend lies right of the axes, over no data
        renderer = fig.canvas.get_renderer()
        assert ax.get_legend().get_window_extent(renderer).x0 >= ax.get_window_extent(renderer).x1
    finally:
        plt.close(fig)
