"""tools/reproduce.py's time accounting: a training resumed after an interruption counts all of its epochs."""

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
    """``make reproduce`` (no flags) is the issue's experiment: 8 houses x 625 frames, bf16, dense 16 epochs and
    sparse 20 (the paper's 250 / 200 ratio)."""
    reproduce = _reproduce()
    assert reproduce.main(["--dry-run", "--out", str(tmp_path / "full")]) == 0
    lines = capsys.readouterr().out.splitlines()
    synth = [ln for ln in lines if " synth " in ln]
    generate = [ln for ln in lines if " generate " in ln]
    train = [ln for ln in lines if " train " in ln]
    assert len(synth) == 1 and "--houses 8" in synth[0]
    assert len(generate) == 1 and "--frames 625" in generate[0]
    assert len(train) == 2 and "--epochs 16 --precision bf16" in train[0] and "dense_cpu" in train[0]
    assert "--epochs 20 --precision bf16" in train[1] and "sparse_cpu" in train[1]

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


def _bench_row(name: str, total: float, head: float, peer: str | None = None) -> dict:
    comps = {k: {"mean_ms": 1.0, "std_ms": 0.0} for k in ("to_device", "feature_extract", "feature_net", "backbone",
                                                          "bbox_extract")}
    comps["head"] = {"mean_ms": head, "std_ms": 0.0}
    comps["total"] = {"mean_ms": total, "std_ms": 0.0}
    return {"name": name, "peer": peer, "components": comps}


def test_bench_step_runs_the_peer_and_the_report_shows_it(tmp_path: Path, capsys) -> None:
    """The bench step asks for the Open3D-ML peer row; the targets table shows peer / ours total-time ratios and the
    shared components' sparse / dense ratios."""
    reproduce = _reproduce()
    assert reproduce.main(["--dry-run", "--scale", "small", "--steps", "bench", "--out", str(tmp_path / "s")]) == 0
    bench = [ln for ln in capsys.readouterr().out.splitlines() if " bench " in ln]
    assert len(bench) == 2 and all(ln.endswith("--peer open3d-ml > " + ln.split(" > ")[-1]) for ln in bench)
    assert bench[1].startswith("$ MALLOC_MMAP_MAX_=0")
    res = tmp_path / "res"
    res.mkdir()
    models = [_bench_row("dense", 1000.0, 50.0), _bench_row("sparse", 250.0, 55.0),
              _bench_row("sparse+sparse_head", 100.0, 2.0), _bench_row("open3d-ml", 1200.0, 150.0, "open3d-ml")]
    (res / "bench_default.json").write_text(json.dumps({"models": models}))
    rows = "\n".join(reproduce._summary(res))
    peer = "| open3d-ml (Open3D-ML's dense) / "
    assert peer + "dense, total time, allocator default | >= 1 (ours no slower) | 1.20x |" in rows
    assert "| open3d-ml (Open3D-ML's dense) / sparse, total time, allocator default | - | 4.80x |" in rows
    assert "open3d-ml (Open3D-ML's dense) / sparse+sparse_head, total time" in rows
    assert "| sparse / dense, head time (same code), allocator default | 0.9 - 1.1 | 1.10x |" in rows
    assert "dense / open3d-ml" not in rows and "sparse+sparse_head / dense, head" not in rows
