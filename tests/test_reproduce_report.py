"""tools/reproduce.py: its time accounting (a training resumed after an interruption counts all of its epochs), its
recipes, and its AP report (Overall and the reference's Open3D-ML metric first, then Easy / Moderate / Hard)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _reproduce():
    spec = importlib.util.spec_from_file_location("reproduce", ROOT / "tools" / "reproduce.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up while the file executes
    spec.loader.exec_module(module)
    return module


def _metrics(run: Path, epoch_seconds: list[float]) -> None:
    run.mkdir(parents=True)
    records = [{"kind": "step", "step": 1, "time_s": 99.0}]  # step records must not be counted again
    records += [{"kind": "epoch", "epoch": i + 1, "time_s": t} for i, t in enumerate(epoch_seconds)]
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))


def test_elapsed_counts_resumed_training_by_its_epochs(tmp_path: Path) -> None:
    out = tmp_path / "reproduce-full"
    log = [
        f"     60.0 s  /v/bin/mpchair generate --root {out}/houses --out {out}/dataset",
        f"   1000.0 s  ENV=1 /v/bin/detector train --config c.yaml --out {out}/runs/dense --threads 2",
        # sparse was cut after 3 of its 5 epochs; only the resumed command (the last 2 epochs) finished and was logged
        f"    250.0 s  ENV=1 /v/bin/detector train --config c.yaml --out {out}/runs/sparse --threads 2 --resume",
        f"     30.0 s  /v/bin/detector eval --checkpoint {out}/runs/sparse/last.pt --split val",
    ]
    out.mkdir()
    (out / "commands.log").write_text("\n".join(log) + "\n")
    _metrics(out / "runs" / "dense", [190.0] * 5)  # 950 s: less than its logged command (start-up, periodic eval)
    _metrics(out / "runs" / "sparse", [120.0] * 5)  # 600 s: the cut part is in the epochs, not in the log
    total, train = _reproduce()._elapsed((out / "commands.log").read_text(), out / "runs")
    assert train == {"dense": 1000.0, "sparse": 600.0}
    assert total == 60.0 + 1000.0 + 600.0 + 30.0


def test_default_reproduction_is_the_measured_full_scale_recipe(tmp_path: Path, capsys) -> None:
    """``make reproduce`` (no flags) is the issue's experiment: 8 houses x 625 frames, dense 16 epochs and sparse 20
    (the paper's 250 / 200 ratio), bf16 where the CPU computes it natively, else fp32."""
    reproduce = _reproduce()
    assert reproduce.main(["--dry-run", "--out", str(tmp_path / "full")]) == 0
    lines = capsys.readouterr().out.splitlines()
    synth = [ln for ln in lines if " synth " in ln]
    generate = [ln for ln in lines if " generate " in ln]
    train = [ln for ln in lines if " train " in ln]
    assert len(synth) == 1 and "--houses 8" in synth[0]
    assert len(generate) == 1 and "--frames 625" in generate[0]
    auto = "bf16" if reproduce.cpu_has_native_bf16() else "fp32"
    assert len(train) == 2 and f"--epochs 16 --precision {auto}" in train[0] and "dense_cpu" in train[0]
    assert f"--epochs 20 --precision {auto}" in train[1] and "sparse_cpu" in train[1]

    # a flag overrides the scale's precision; the quick scale keeps the configs' precision
    assert reproduce.main(["--dry-run", "--precision", "fp32", "--out", str(tmp_path / "fp32")]) == 0
    train = [ln for ln in capsys.readouterr().out.splitlines() if " train " in ln]
    assert len(train) == 2 and train[0].endswith("--epochs 16 --precision fp32")
    assert train[1].endswith("--epochs 20 --precision fp32")
    assert reproduce.main(["--dry-run", "--scale", "small", "--out", str(tmp_path / "small")]) == 0
    train = [ln for ln in capsys.readouterr().out.splitlines() if " train " in ln]
    assert len(train) == 2 and train[0].endswith("--epochs 2") and train[1].endswith("--epochs 3")


def test_quick_scale_report_stays_in_its_work_folder(tmp_path: Path, capsys) -> None:
    """Only ``--scale full`` replaces the committed docs/results.md; a small run writes <work folder>/results.md."""
    reproduce = _reproduce()
    committed = (ROOT / "docs" / "results.md").read_bytes()
    assert reproduce.main(["--scale", "small", "--steps", "report", "--out", str(tmp_path / "small")]) == 0
    report = (tmp_path / "small" / "results.md").read_text()
    assert report.startswith("# Results") and "`tools/reproduce.py --scale small`" in report
    assert f"wrote {tmp_path.resolve() / 'small' / 'results.md'}" in capsys.readouterr().out
    assert (ROOT / "docs" / "results.md").read_bytes() == committed


def test_auto_precision_reads_the_cpu_flags(tmp_path: Path) -> None:
    """bf16 only where the CPU has native bfloat16 (AVX512-BF16 or AMX-BF16); missing cpuinfo means fp32."""
    reproduce = _reproduce()
    amd = tmp_path / "amd"
    amd.write_text("processor : 0\nflags : fpu sse4_2 avx avx2 fma\n")
    intel = tmp_path / "spr"
    intel.write_text("processor : 0\nflags : fpu avx2 avx512f avx512_bf16 amx_tile amx_bf16\n")
    assert not reproduce.cpu_has_native_bf16(amd)
    assert reproduce.cpu_has_native_bf16(intel)
    assert not reproduce.cpu_has_native_bf16(tmp_path / "missing")


def _kitti_json(easy: float, overall: float, n: int = 100) -> dict:
    """A KITTI metrics.json of Chair: AP easy / easy+1 / easy+2 (Easy / Moderate / Hard), R11 = R40 - 0.5, and
    ``overall`` (BEV = 3D + 3)."""
    out = {"Chair": {}}
    for kind, extra in (("bbox", 5.0), ("bev", 3.0), ("3d", 0.0), ("aos", 5.0)):
        r40 = [easy + extra, easy + extra + 1, easy + extra + 2]
        out["Chair"][kind] = {"R11": [x - 0.5 for x in r40], "R40": r40,
                              "overall": {"R11": overall + extra - 0.5, "R40": overall + extra}}
    out["num_gt"] = {"Chair": [n // 2, n // 2 + 6, n // 2 + 10]}
    out["num_gt_overall"] = {"Chair": n}
    return out


def test_report_leads_with_overall_and_the_reference_metric(tmp_path: Path) -> None:
    """The detection section and the targets open with Overall (R40, R11) and Open3D-ML's mAP for both models, then
    Easy / Moderate / Hard; the paper's numbers sit beside Overall."""
    reproduce = _reproduce()
    out = tmp_path / "reproduce-small"
    res = out / "results"
    for m, easy, overall, o3d in (("dense", 60.0, 70.0, (81.5, 79.25)), ("sparse", 58.0, 68.0, (77.0, 75.5))):
        (res / f"eval_{m}").mkdir(parents=True)
        (res / f"eval_{m}" / "metrics.json").write_text(json.dumps(_kitti_json(easy, overall)))
        (res / f"eval_{m}" / "open3d_ml.json").write_text(json.dumps(
            {"protocol": "open3d-ml", "Chair": {"bev": o3d[0], "3d": o3d[1]}, "num_gt": {"Chair": 100}}))
    report_path = tmp_path / "results.md"
    reproduce.write_report(report_path, out, res, "small", reproduce.SCALES["small"])
    text = report_path.read_text()
    lines = text.splitlines()

    targets = lines.index("| quantity | target | measured |")
    assert "one AP per metric" in lines[targets - 2] and "**Overall**" in lines[targets - 2]
    assert lines[targets + 2:targets + 10] == [
        "| dense 3D AP, Overall R40 | >= 80 (paper 80.66) | 70.00 |",
        "| sparse - dense, 3D AP Overall R40 | >= -5 (paper -4.61) | -2.00 |",
        "| dense 3D AP, Open3D-ML mAP (the paper's metric) | paper 80.66 | 79.25 |",
        "| sparse - dense, 3D AP Open3D-ML mAP | paper -4.61 | -3.75 |",
        "| dense BEV AP, Overall R40 | paper 84.09 | 73.00 |",
        "| sparse - dense, BEV AP Overall R40 | paper -6.04 | -2.00 |",
        "| dense BEV AP, Open3D-ML mAP (the paper's metric) | paper 84.09 | 81.50 |",
        "| sparse - dense, BEV AP Open3D-ML mAP | paper -6.04 | -4.50 |",
    ]

    detection = lines.index("## Detection (val split, Chair, IoU 0.5)")
    head = next(i for i in range(detection, len(lines)) if lines[i].startswith("| model |"))
    assert lines[head] == ("| model | BEV AP Overall R40 | 3D AP Overall R40 | BEV AP Overall R11 | "
                           "3D AP Overall R11 | BEV AP Open3D-ML mAP | 3D AP Open3D-ML mAP |")
    assert lines[head + 2:head + 5] == [
        "| dense | 73.00 | 70.00 | 72.50 | 69.50 | 81.50 | 79.25 |",
        "| sparse | 71.00 | 68.00 | 70.50 | 67.50 | 77.00 | 75.50 |",
        "| sparse - dense | -2.00 | -2.00 | -2.00 | -2.00 | -4.50 | -3.75 |",
    ]
    levels = lines.index("| model | BEV AP R40 | 3D AP R40 | BEV AP R11 | 3D AP R11 |")
    assert head < levels and "Easy / Moderate / Hard" in lines[levels - 2]
    assert lines[levels + 2] == "| dense | 63.00 / 64.00 / 65.00 | 60.00 / 61.00 / 62.00 | 62.50 / 63.50 / 64.50 | " \
                                "59.50 / 60.50 / 61.50 |"
    assert "Valid GT chairs: Easy 50, Moderate 56, Hard 60, Overall 100 (Moderate ignores 44 % of the chairs)." in text
    assert text.index("Paper (real Matterport-Chair, Open3D-ML mAP, one level)") < text.index(lines[levels])


def test_report_reads_metrics_without_overall_or_open3d_ml(tmp_path: Path) -> None:
    """A metrics.json written before the Overall level (and no open3d_ml.json) still gives a report, with n/a."""
    reproduce = _reproduce()
    out = tmp_path / "reproduce-small"
    res = out / "results"
    old = _kitti_json(60.0, 70.0)
    for kind in ("bbox", "bev", "3d", "aos"):
        del old["Chair"][kind]["overall"]
    del old["num_gt_overall"]
    (res / "eval_dense").mkdir(parents=True)
    (res / "eval_dense" / "metrics.json").write_text(json.dumps(old))
    reproduce.write_report(tmp_path / "results.md", out, res, "small", reproduce.SCALES["small"])
    text = (tmp_path / "results.md").read_text()
    assert "| dense | n/a | n/a | n/a | n/a | n/a | n/a |" in text and "| sparse | not run | | | | | |" in text
    assert "| dense | 63.00 / 64.00 / 65.00 |" in text and "Valid GT chairs: Easy 50, Moderate 56, Hard 60." in text


def test_eval_step_also_runs_the_reference_metric_on_the_same_result_files(tmp_path: Path, capsys) -> None:
    reproduce = _reproduce()
    out = tmp_path / "small"
    assert reproduce.main(["--dry-run", "--scale", "small", "--steps", "eval", "--out", str(out)]) == 0
    evals = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("$ ") and " eval " in ln]
    assert len(evals) == 4
    for m, (kitti, o3d) in zip(("dense", "sparse"), (evals[:2], evals[2:])):
        assert f"--checkpoint {out.resolve()}/runs/{m}/last.pt" in kitti and "--protocol" not in kitti
        assert f"--results {out.resolve()}/results/eval_{m}/data " in o3d and "--protocol open3d-ml --json" in o3d
        assert o3d.endswith(f"> {out.resolve()}/results/eval_{m}/open3d_ml.json")
