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
