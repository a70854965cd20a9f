"""reproduction (``tools/reproduce.py``): the recipe's commands, its time accounting (a training resumed after
an interruption counts all of its epochs), its AP report (Overall and the reference's Open3D-ML metric first, then
Easy / Moderate / Hard), and the report written from the outputs of real (tiny) runs of those commands."""

from __future__ import annotations

import dataclasses
import json
import re
import shlex
import time
from pathlib import Path

import pytest
from helpers_detector import make_tiny_dataset, write_manifest, write_run_config, write_test_config

from detector.bench.result import BenchResult
from mpchair.kitti import read_imageset
from reproduction import steps
from reproduction.cli import main
from reproduction.report import targets_section, write_report
from reproduction.scales import SCALES, Scale, cpu_has_native_bf16, model_epochs
from reproduction.status import status_lines
from reproduction.training import elapsed_seconds

ROOT = Path(__file__).resolve().parents[1]


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
    total, train = elapsed_seconds((out / "commands.log").read_text(), out / "runs")
    assert train == {"dense": 1000.0, "sparse": 600.0}
    assert total == 60.0 + 1000.0 + 600.0 + 30.0


def _started_run(out: Path, model: str, steps: int, precision: str = "fp32") -> Path:
    """A work folder's run of ``model`` stopped after ``steps`` steps of 1.5 s (2 epochs of 10 frames, batch 2)."""
    run = out / "runs" / model
    run.mkdir(parents=True)
    write_run_config(run, train={"epochs": 2, "batch_size": 2, "samples_per_epoch": None, "precision": precision})
    records = [{"kind": "step", "epoch": 1 + (i - 1) // 5, "step": i, "time_s": 1.5} for i in range(1, steps + 1)]
    # the last line torn, as kill -9 may leave it
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records) + '{"kind": "st')
    (run / "last.pt").write_bytes(b"")
    return run


def test_status_shows_each_step_and_where_training_stands(tmp_path: Path, capsys) -> None:
    """--status: done steps, a model's step of its total with the time left at its pace, and whether a process holds
    its run folder's lock right now."""
    from mpchair.core.lock import folder_lock

    out = tmp_path / "w"
    (out / "dataset" / "ImageSets").mkdir(parents=True)
    (out / "dataset" / "ImageSets" / "train.txt").write_text("".join(f"{i:06d}\n" for i in range(10)))
    write_manifest(out / "dataset", {"h0": (0, 9, {})})
    run = _started_run(out, "dense", steps=6)
    assert main(["--status", "--out", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"{out}:" and "  synth     0 of 1 outputs" in lines and "  generate  done" in lines
    assert "  train     0 of 2 outputs" in lines
    assert "    dense: step 6 / 10 (epoch 2 of 2), 1.50 s/step lately -> ~6 s left; stopped (the same command " \
           "resumes it)" in lines
    assert "    sparse: not started" in lines
    with folder_lock(run / ".train.lock", "detector train"):
        text = "\n".join(status_lines(out))
    assert "dense: step 6 / 10 (epoch 2 of 2), 1.50 s/step lately -> ~6 s left; running now" in text
    (run / "done").write_text("trained\n")
    assert "    dense: trained" in status_lines(out)
    assert status_lines(tmp_path / "none") == [f"{tmp_path / 'none'}: no reproduction here yet"]


def test_a_run_resumes_in_the_precision_it_started_with(tmp_path: Path, capsys) -> None:
    """A session on a CPU where ``auto`` resolves otherwise must not hand the resumed run another precision (detector
    train would refuse the changed config); a run not yet started takes the scale's."""
    out = tmp_path / "w"
    _started_run(out, "dense", steps=3, precision="fp32")
    assert main(["--dry-run", "--scale", "small", "--steps", "train", "--precision", "bf16", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    train = [ln for ln in printed.splitlines() if " train " in ln and ln.startswith("$ ")]
    assert "--resume" in train[0] and train[0].endswith("--precision fp32") and "/runs/dense " in train[0]
    assert "dense: resuming in fp32, the precision this run started with (not bf16)" in printed
    assert "--resume" not in train[1] and train[1].endswith("--precision bf16")


def test_default_reproduction_is_the_one_session_full_scale(tmp_path: Path, capsys) -> None:
    """``make reproduce`` (no flags) is the issue's experiment on the one-session schedule: 12 houses x 400 frames
    split 8 / 2 / 2 by house, dense 4 epochs and sparse 5 (the paper's 250 / 200 ratio), bf16 where the CPU computes
    it natively, else fp32; ``--scale recipe`` is the same data with dense 16 / sparse 20 epochs."""
    assert main(["--dry-run", "--out", str(tmp_path / "full")]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("$ ")]  # the commands
    synth = [ln for ln in lines if " synth " in ln]
    generate = [ln for ln in lines if " generate " in ln]
    train = [ln for ln in lines if " train " in ln]
    assert len(synth) == 1 and "--houses 12" in synth[0]
    assert len(generate) == 1 and "--frames 400" in generate[0] and "--split-mode house" in generate[0]
    auto = "bf16" if cpu_has_native_bf16() else "fp32"
    assert len(train) == 2 and f"--epochs 4 --precision {auto}" in train[0] and "dense_cpu" in train[0]
    assert f"--epochs 5 --precision {auto}" in train[1] and "sparse_cpu" in train[1]
    assert main(["--dry-run", "--scale", "recipe", "--out", str(tmp_path / "recipe")]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("$ ")]
    train = [ln for ln in lines if " train " in ln]
    assert any(" generate " in ln and "--frames 400 " in ln and "--split-mode house" in ln for ln in lines)
    assert len(train) == 2 and f"--epochs 16 --precision {auto}" in train[0]
    assert f"--epochs 20 --precision {auto}" in train[1]

    # a flag overrides the scale's precision; the quick scale keeps the configs' precision
    assert main(["--dry-run", "--precision", "fp32", "--out", str(tmp_path / "fp32")]) == 0
    train = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("$ ") and " train " in ln]
    assert len(train) == 2 and train[0].endswith("--epochs 4 --precision fp32")
    assert train[1].endswith("--epochs 5 --precision fp32")
    assert main(["--dry-run", "--scale", "small", "--out", str(tmp_path / "small")]) == 0
    train = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("$ ") and " train " in ln]
    assert len(train) == 2 and train[0].endswith("--epochs 2") and train[1].endswith("--epochs 3")


def test_quick_scale_report_stays_in_its_work_folder(tmp_path: Path, capsys) -> None:
    """Only ``--scale full`` replaces the committed docs/results.md; a small run writes <work folder>/results.md."""
    committed = (ROOT / "docs" / "results.md").read_bytes()
    assert main(["--scale", "small", "--steps", "report", "--out", str(tmp_path / "small")]) == 0
    report = (tmp_path / "small" / "results.md").read_text()
    assert report.startswith("# Results") and "`tools/reproduce.py --scale small`" in report
    assert f"wrote {tmp_path.resolve() / 'small' / 'results.md'}" in capsys.readouterr().out
    assert (ROOT / "docs" / "results.md").read_bytes() == committed


@pytest.mark.slow
def test_train_step_shows_each_epoch_as_it_runs(tmp_path: Path, capfd, monkeypatch) -> None:
    """The train step runs ``detector train --no-progress`` as a child process, and its plan, estimate and per-epoch
    lines reach the terminal (it was silent for minutes). Here the sparse model's training only (the dense one is
    marked done), with the slim test model on a tiny dataset, renamed as the recipe's CPU config."""
    configs = tmp_path / "configs"
    configs.mkdir()
    write_test_config(configs / "mpchair_sparse_cpu.yaml", model=dict(backbone="sparse"), train=dict(batch_size=2))
    monkeypatch.setattr(steps, "CONFIGS", configs)
    out = tmp_path / "reproduce-small"
    make_tiny_dataset(out / "dataset", n_frames=6, seed=1)  # 3 steps per epoch
    (out / "runs" / "dense").mkdir(parents=True)
    (out / "runs" / "dense" / "done").write_text("trained\n")
    assert main(["--scale", "small", "--steps", "train", "--epochs", "1", "--threads", "1", "--out", str(out)]) == 0
    lines = capfd.readouterr().out.splitlines()
    # the sparse model trains ceil(1.25 x 1) = 2 epochs; its lines follow its command line, as they come
    (start,) = [i for i, ln in enumerate(lines) if ln.startswith("$ ") and " train " in ln]
    assert "sparse_cpu" in lines[start] and "--no-progress" in lines[start]
    child = lines[start + 1 :]
    assert child[0] == "training 6 step(s): 2 epochs x 3 steps (global batch 2); timing the first steps..."
    assert child[1].startswith("epoch 1/2: loss ")
    # the estimate comes after step 4, here inside epoch 2
    assert re.fullmatch(r"6 steps, ~\d+\.\d\d s/step measured -> ~.+", child[2]), child[2]
    assert child[3].startswith("epoch 2/2: loss ")
    assert child[4].startswith("trained 2 epoch(s), 6 step(s)") and (out / "runs" / "sparse" / "done").is_file()


def test_auto_precision_reads_the_cpu_flags(tmp_path: Path) -> None:
    """bf16 only where the CPU has native bfloat16 (AVX512-BF16 or AMX-BF16); missing cpuinfo means fp32."""
    amd = tmp_path / "amd"
    amd.write_text("processor : 0\nflags : fpu sse4_2 avx avx2 fma\n")
    intel = tmp_path / "spr"
    intel.write_text("processor : 0\nflags : fpu avx2 avx512f avx512_bf16 amx_tile amx_bf16\n")
    assert not cpu_has_native_bf16(amd)
    assert cpu_has_native_bf16(intel)
    assert not cpu_has_native_bf16(tmp_path / "missing")


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
    out = tmp_path / "reproduce-small"
    res = out / "results"
    for m, easy, overall, o3d in (("dense", 60.0, 70.0, (81.5, 79.25)), ("sparse", 58.0, 68.0, (77.0, 75.5))):
        (res / f"eval_{m}").mkdir(parents=True)
        (res / f"eval_{m}" / "metrics.json").write_text(json.dumps(_kitti_json(easy, overall)))
        (res / f"eval_{m}" / "open3d_ml.json").write_text(json.dumps(
            {"protocol": "open3d-ml", "Chair": {"bev": o3d[0], "3d": o3d[1]}, "num_gt": {"Chair": 100}}))
    report_path = tmp_path / "results.md"
    write_report(report_path, out, res, "small", SCALES["small"])
    text = report_path.read_text()
    lines = text.splitlines()

    targets = lines.index("| quantity | target | measured |")
    assert "one AP per metric" in lines[targets - 2] and "**Overall**" in lines[targets - 2]
    assert lines[targets + 2:targets + 10] == [
        "| dense 3D AP, Overall R40 | >= 80 (paper 80.66) | 70.00 |",
        "| sparse - dense, 3D AP Overall R40 | paper -4.61 (one seed, no interval) | -2.00 |",
        "| dense 3D AP, Open3D-ML mAP (the paper's metric, recall-blind) | paper 80.66 | 79.25 |",
        "| sparse - dense, 3D AP Open3D-ML mAP | paper -4.61 | -3.75 |",
        "| dense BEV AP, Overall R40 | paper 84.09 | 73.00 |",
        "| sparse - dense, BEV AP Overall R40 | paper -6.04 (one seed, no interval) | -2.00 |",
        "| dense BEV AP, Open3D-ML mAP (the paper's metric, recall-blind) | paper 84.09 | 81.50 |",
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
    paper = text.index("Paper (real Matterport-Chair, Open3D-ML mAP, recall-blind, one level)")
    assert paper < text.index(lines[levels])
    # the paper's gap on its own metric: -3.75 against -4.61 is within a point; the KITTI half-found case at 100 GT
    assert ("this run's sparse - dense 3D gap is -3.75 against the paper's -4.61: close to it, but one seed per "
            "model") in text
    assert ("finding half of the chairs perfectly scores 100 there and R40 50 on the KITTI level with this val set's "
            "100 chairs (R40 10 with 10 ground-truth boxes") in text
    recall_blind = next(ln for ln in lines[head:levels] if ln.startswith("Open3D-ML's mAP is recall-blind"))
    assert "above its BEV AP" not in recall_blind  # 79.25 < 81.5 and 75.5 < 77: nothing to point at


def test_report_says_when_the_reference_metric_is_not_monotone_and_the_gap_not_reproduced(tmp_path: Path) -> None:
    """results.md's case: Open3D-ML's 3D mAP above its BEV mAP (recall-blind, said with the numbers), and a sparse -
    dense gap of +0.36 on the paper's metric, which is not the paper's -4.61."""
    out = tmp_path / "reproduce-small"
    res = out / "results"
    for m, o3d in (("dense", (87.37, 88.36)), ("sparse", (87.70, 88.72))):
        (res / f"eval_{m}").mkdir(parents=True)
        (res / f"eval_{m}" / "metrics.json").write_text(json.dumps(_kitti_json(60.0, 70.0, n=1833)))
        (res / f"eval_{m}" / "open3d_ml.json").write_text(json.dumps(
            {"protocol": "open3d-ml", "Chair": {"bev": o3d[0], "3d": o3d[1]}, "num_gt": {"Chair": 1833}}))
    write_report(tmp_path / "results.md", out, res, "small", SCALES["small"])
    text = (tmp_path / "results.md").read_text()
    assert ("its 3D AP comes out above its BEV AP (dense 88.36 > 87.37, sparse 88.72 > 87.70), impossible for a "
            "monotone metric") in text
    assert "3D gap is +0.36 against the paper's -4.61: apart from it, but one seed per model" in text
    assert "with no interval, cannot tell a real difference from training noise" in text and "inconclusive" in text
    assert "R40 50 on the KITTI level with this val set's 1,833 chairs" in text
    assert "## Targets and this run" in text and "(issue)" not in text


@pytest.mark.parametrize(("num_gt", "r40"), [(10, 10.0), (40, 47.5), (100, 50.0), (1833, 50.0)])
def test_half_found_r40_is_what_the_kitti_protocol_gives(num_gt: int, r40: float) -> None:
    """The figure the report quotes for "finding half of the chairs perfectly" equals the KITTI protocol's own result
    on such a case (``detector.eval.evaluate``: num_gt chairs, 10 per frame, the first half detected exactly)."""
    import numpy as np

    from detector.eval import evaluate
    from mpchair.kitti import Labels
    from reproduction.report import half_found_r40

    def labels(n: int, scores: np.ndarray | None = None) -> Labels:
        loc = np.array([[-3.0 + 1.5 * (i % 5), 1.0, 5.0 + 2.0 * (i // 5)] for i in range(n)]).reshape(-1, 3)
        return Labels(names=["Chair"] * n, truncated=np.zeros(n), occluded=np.zeros(n), alpha=np.zeros(n),
                      bbox=np.tile([100.0, 100.0, 200.0, 200.0], (n, 1)), dims_hwl=np.tile([0.9, 0.55, 0.6], (n, 1)),
                      location=loc, rotation_y=np.zeros(n), score=scores)

    per_frame = [min(10, num_gt - i) for i in range(0, num_gt, 10)]
    gt = [labels(k) for k in per_frame]
    found, dt = num_gt // 2, []
    for k in per_frame:  # the first `found` chairs over the frames, each exactly, with distinct scores
        take = max(0, min(k, found - 10 * len(dt)))
        dt.append(labels(take, np.linspace(0.99, 0.5, take) - 1e-4 * len(dt)) if take else labels(0, np.zeros(0)))
    overall = evaluate(gt, dt, ["Chair"]).overall["Chair"]
    assert overall["3d"]["R40"] == pytest.approx(r40) and half_found_r40(num_gt) == pytest.approx(r40)


def test_report_reads_metrics_without_overall_or_open3d_ml(tmp_path: Path) -> None:
    """A metrics.json written before the Overall level (and no open3d_ml.json) still gives a report, with n/a."""
    out = tmp_path / "reproduce-small"
    res = out / "results"
    old = _kitti_json(60.0, 70.0)
    for kind in ("bbox", "bev", "3d", "aos"):
        del old["Chair"][kind]["overall"]
    del old["num_gt_overall"]
    (res / "eval_dense").mkdir(parents=True)
    (res / "eval_dense" / "metrics.json").write_text(json.dumps(old))
    write_report(tmp_path / "results.md", out, res, "small", SCALES["small"])
    text = (tmp_path / "results.md").read_text()
    assert "| dense | n/a | n/a | n/a | n/a | n/a | n/a |" in text and "| sparse | not run | | | | | |" in text
    assert "| dense | 63.00 / 64.00 / 65.00 |" in text and "Valid GT chairs: Easy 50, Moderate 56, Hard 60." in text


def test_a_full_scale_run_cut_short_says_so(tmp_path: Path) -> None:
    """A full-scale report of fewer training samples than the recipe says that it is short, gives each model's epochs x
    samples and the sparse/dense ratio it actually trained, and carries the operator's notes; the recipe's own
    schedule keeps the plain wording."""
    out = tmp_path / "reproduce-full"
    (out / "dataset" / "ImageSets").mkdir(parents=True)
    (out / "dataset" / "ImageSets" / "train.txt").write_text("".join(f"{i:06d}\n" for i in range(10)))

    def runs(*schedules: tuple[int, int | None]) -> str:
        for m, (epochs, spe) in zip(("dense", "sparse"), schedules):
            write_run_config(out / "runs" / m, train={"epochs": epochs, "samples_per_epoch": spe, "batch_size": 2})
        sc = dataclasses.replace(SCALES["full"], epochs=1)
        write_report(tmp_path / "results.md", out, out / "results", "full", sc,
                     notes=["The two trainings ran one after the other."])
        return (tmp_path / "results.md").read_text()

    text = runs((1, 4), (1, 5))
    assert "**This run is shorter than the recipe:** it trained dense 1 epoch x 4 samples / sparse 1 epoch x 5 " \
           "samples instead of dense 16 / sparse 20 epochs x 10 samples" in text
    assert "training dense 1 epoch x 4 samples / sparse 1 epoch x 5 samples, precision" in text.splitlines()[2]
    schedule = next(ln for ln in text.splitlines() if ln.startswith("| schedule |"))
    assert "not converged" in schedule and "1.25 sparse/dense ratio is kept" in schedule
    assert text.splitlines()[2].endswith("The two trainings ran one after the other.")

    schedule = next(ln for ln in runs((1, None), (2, None)).splitlines() if ln.startswith("| schedule |"))
    assert "dense 1 epoch x 10 samples / sparse 2 epochs x 10 samples" in schedule
    assert "ratio of training samples 2.00" in schedule

    text = runs((16, None), (20, None))
    schedule = next(ln for ln in text.splitlines() if ln.startswith("| schedule |"))
    assert "shorter than the recipe" not in text and "not converged" not in schedule
    assert "1.25 sparse/dense ratio is kept" in schedule


def test_eval_step_also_runs_the_reference_metric_on_the_same_result_files(tmp_path: Path, capsys) -> None:
    out = tmp_path / "small"
    assert main(["--dry-run", "--scale", "small", "--steps", "eval", "--out", str(out)]) == 0
    evals = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("$ ") and " eval " in ln]
    assert len(evals) == 4
    for m, (kitti, o3d) in zip(("dense", "sparse"), (evals[:2], evals[2:])):
        assert f"--checkpoint {out.resolve()}/runs/{m}/last.pt" in kitti and "--protocol" not in kitti
        assert f"--results {out.resolve()}/results/eval_{m}/data " in o3d and "--protocol open3d-ml --json" in o3d
        assert o3d.endswith(f"> {out.resolve()}/results/eval_{m}/open3d_ml.json")
@pytest.mark.slow
def test_report_carries_the_numbers_of_real_outputs(tmp_path: Path, capsys) -> None:
    """``write_report`` on what the recipe's commands really write, here for a tiny run (4 frames; dense and sparse
    slim test models, 2 and 3 epochs with validation after every epoch; bench, ops and viz on 1-2 frames): every
    table and figure carries the numbers and pictures of those outputs, and the commands are listed. The second
    allocator's bench is left out, so its section must say so."""
    from detector.cli import main as detector_main
    from mpchair.cli import main as mpchair_main

    out = tmp_path / "reproduce-small"
    data = make_tiny_dataset(out / "dataset", n_frames=4, seed=1)
    res, runs = out / "results", out / "runs"
    epochs = model_epochs(2)  # dense 2, sparse 3 (the recipe's 1.25 ratio)
    # score threshold 0: the scores of so short a run stay under the default 0.1 (no AP, empty result files)
    cfg = {m: write_test_config(tmp_path / f"{m}.yaml", model=dict(backbone=m, score_thr=0.0),
                                train=dict(batch_size=2, epochs=epochs[m], eval_every=1)) for m in ("dense", "sparse")}

    def run(prog: str, *args, stdout: Path | None = None) -> None:
        """Run a console script in this process and log it as reproduction's Runner does."""
        t = time.perf_counter()
        with pytest.raises(SystemExit) as e:
            (mpchair_main if prog == "mpchair" else detector_main)([str(a) for a in args])
        captured = capsys.readouterr()
        assert e.value.code == 0, captured.err
        if stdout is not None:
            stdout.parent.mkdir(parents=True, exist_ok=True)
            stdout.write_text(captured.out)
        line = shlex.join([prog, *map(str, args)]) + (f" > {stdout}" if stdout else "")
        with open(out / "commands.log", "a") as f:
            f.write(f"{time.perf_counter() - t:9.1f} s  {line}\n")

    run("mpchair", "stats", "--density", data, "--config", cfg["dense"], "--split", "test", "--plot",
        res / "density.png")
    run("mpchair", "stats", "--density", data, "--config", cfg["dense"], "--split", "test", "--json",
        stdout=res / "density.json")
    for m in ("dense", "sparse"):
        run("detector", "train", "--config", cfg[m], "--data", data, "--out", runs / m, "--threads", "1",
            "--no-progress")
    for m in ("dense", "sparse"):
        run("detector", "eval", "--config", cfg[m], "--data", data, "--checkpoint", runs / m / "last.pt", "--split",
            "val", "--out", res / f"eval_{m}", "--threads", "1")
    run("detector", "bench", "--config", cfg["dense"], "--config", cfg["sparse"], "--data", data, "--split", "test",
        "--frames", "1", "--trials", "1", "--warmup", "0", "--threads", "1", "--json-out", res / "bench_default.json",
        "--markdown", "--checkpoint", runs / "dense" / "last.pt", "--checkpoint", runs / "sparse" / "last.pt",
        stdout=res / "bench_default.md")
    run("detector", "ops", "--config", cfg["sparse"], "--data", data, "--split", "test", "--frames", "2", "--out",
        res / "ops.json", "--markdown", stdout=res / "ops.md")
    run("detector", "viz-sparsity", "--config", cfg["sparse"], "--data", data, "--index", "0", "--split", "test",
        "--out", res / "viz", "--json", stdout=res / "viz.json")

    sc = Scale(houses=1, frames_per_house=4, epochs=2, bench_frames=1, bench_trials=1, ops_frames=2)
    # the released code's sensor height and the navmesh agent's radius, as `mpchair generate` records its settings
    write_manifest(data, {"h0": (0, 3, {"h0.ply": "0" * 64})}, height=1.25, robot_radius=0.1)
    report_path = tmp_path / "docs" / "results.md"
    write_report(report_path, out, res, "small", sc)
    report = report_path.read_text()
    lines = report.splitlines()

    def row(start: str) -> str:
        (found,) = [ln for ln in lines if ln.startswith(start)]
        return found

    def section(title: str) -> str:
        """The text under the ``## title...`` heading, up to the next heading."""
        return report.split(f"\n## {title}", 1)[1].split("\n", 1)[1].split("\n## ", 1)[0]

    assert report.startswith("# Results") and "1 synthetic houses x 4 frames" in report
    ntr = len(read_imageset(data / "ImageSets" / "train.txt"))
    trained = f"dense 2 epochs x {ntr:,} samples / sparse 3 epochs x {ntr:,} samples"
    assert f"training {trained}, precision fp32" in report
    # AP: the eval outputs' Overall level in the targets; Overall and then Easy / Moderate / Hard in the detection
    # section, one row per model in each table
    ev = {m: json.loads((res / f"eval_{m}" / "metrics.json").read_text())["Chair"] for m in ("dense", "sparse")}
    d3, s3 = ev["dense"]["3d"]["overall"]["R40"], ev["sparse"]["3d"]["overall"]["R40"]
    assert row("| dense 3D AP, Overall R40 |").endswith(f"| {d3:.2f} |")
    assert row("| sparse - dense, 3D AP Overall R40 |").endswith(f"| {s3 - d3:+.2f} |")
    for m in ("dense", "sparse"):
        first, levels = [ln for ln in section("Detection").splitlines() if ln.startswith(f"| {m} |")][:2]
        for kind in ("bev", "3d"):
            for recall in ("R40", "R11"):
                assert f"{ev[m][kind]['overall'][recall]:.2f}" in first, (m, kind, recall)
                assert " / ".join(f"{v:.2f}" for v in ev[m][kind][recall][:3]) in levels, (m, kind, recall)
    # the validation records of both training logs (every epoch), Moderate BEV and 3D AP
    for m in ("dense", "sparse"):
        evals = [json.loads(x) for x in (runs / m / "metrics.jsonl").read_text().splitlines()]
        evals = [e for e in evals if e["kind"] == "eval"]
        assert [e["epoch"] for e in evals] == list(range(1, epochs[m] + 1))
        for e in evals:
            ap = e["Chair"]
            assert (f"| {m} | {e['epoch']} | {ap['bev']['overall']['R40']:.2f} | {ap['3d']['overall']['R40']:.2f} | "
                    f"{ap['bev']['R40'][1]:.2f} | {ap['3d']['R40'][1]:.2f} |") in lines
    # the differences from the paper's experiment, read from this run's manifest and run configs
    diff = section("Differences from the paper's experiment")
    n = {k: len(read_imageset(data / "ImageSets" / f"{k}.txt")) for k in ("train", "val", "test")}
    assert f"train {n['train']:,} / val {n['val']:,} / test {n['test']:,}" in diff
    assert trained in diff and "| precision | fp32 (GPU) | fp32 (dense) / fp32 (sparse) |" in diff
    assert "| realism model | real reconstructions: holes" in diff
    table = diff.strip().split("\n\n")[0].splitlines()
    assert len(table) == 2 + 16 and all(len(ln.split(" | ")) == 4 for ln in table[2:])  # 4 cells, no stray "|"
    # ... and the ways the models and measurements differ from where the paper's numbers came from
    median = json.loads((res / "density.json").read_text())["median"]
    viz = json.loads((res / "viz.json").read_text())
    cells = {ln.split(" | ")[0][2:]: ln.split(" | ")[2] for ln in table[2:]}
    assert cells["sensor height"] == "1.25 m (`mpchair generate --height`)"
    assert cells["robot radius"].startswith("0.1 m: ")
    assert cells["gradient clipping"] == "total norm 10" and cells["sparse down-conv"].startswith("`downsample: floor`")
    assert cells["density D (test split)"] == f"median {median:.5f} (`mpchair stats`)"
    assert cells["sparsity figures (Figs. 3-4)"] == (f"test frame {viz['frame_id']}, a Matterport-Chair frame of "
                                                     f"D = {viz['nonzero_fraction']['dense'][0]:.5f}")
    assert cells["bench weights"].startswith("this run's, trained on the ") and "768 x 512 model" in cells[
        "bench weights"]
    assert "fused into one 1x1 GEMM" in cells["head at inference"]
    # density: the stats summary, and the plot copied next to the report
    summary = json.loads((res / "density.json").read_text())  # D per test frame: median, min, max, ...
    assert json.dumps({k: summary[k] for k in ("median", "min", "max")}) in section("Density")
    assert "![density](img/results-small/density.png)" in lines
    assert (tmp_path / "docs" / "img" / "results-small" / "density.png").read_bytes() == (
        res / "density.png").read_bytes()
    # runtime: the bench table as printed, the dense / sparse ratios of its JSON; the other allocator was not run
    assert (res / "bench_default.md").read_text().strip() in section("Runtime at 768 x 512, allocator default")
    assert section("Runtime at 768 x 512, allocator reuse").strip().startswith("not run")
    comps = {m["name"]: m["components"] for m in json.loads((res / "bench_default.json").read_text())["models"]}
    for comp in ("backbone", "total"):
        ratio = comps["dense"][comp]["mean_ms"] / comps["sparse"][comp]["mean_ms"]
        assert row(f"| dense / sparse, {comp} time, allocator default |").endswith(f"| {ratio:.1f}x |")
    # op counts and the sparsity figure
    ops = (res / "ops.md").read_text().strip()
    assert ops.startswith("MACs per frame") and ops in section("Operation counts (Table I)")
    assert "![sparsity](img/results-small/sparsity.png)" in section("Sparsity figures (Figs. 3-4)")
    assert (tmp_path / "docs" / "img" / "results-small" / "sparsity.png").read_bytes() == (
        res / "viz" / "panel.png").read_bytes()
    # every command, as logged
    commands = section("Commands")
    for line in (out / "commands.log").read_text().splitlines():
        assert line in commands


def test_shared_components_show_the_ratio_of_per_frame_medians_beside_the_means(tmp_path: Path) -> None:
    """A few-ms shared component is judged by two numbers: the ratio of means (which one hiccup moves) and the ratio of
    the per-frame medians, from the bench JSON's ``median_frame_ms``."""
    dense, sparse = _bench_row("dense", 1000.0, 50.0), _bench_row("sparse", 250.0, 55.0)
    dense["median_frame_ms"] = {**{k: 1.0 for k in dense["components"]}, "head": 50.0, "bbox_extract": 8.0}
    sparse["median_frame_ms"] = {**{k: 1.0 for k in sparse["components"]}, "head": 47.5, "bbox_extract": 6.0}
    (tmp_path / "bench_reuse.json").write_text(json.dumps({"models": [dense, sparse]}))
    rows = targets_section(tmp_path)
    assert "| sparse / dense, head time (same code), allocator reuse | 0.9 - 1.1 | 1.10x (median 0.95x) |" in rows
    bbox = "| sparse / dense, bbox_extract time (same code), allocator reuse | 0.9 - 1.1 |"
    assert bbox + " 1.00x (median 0.75x) |" in rows


def test_head_and_bbox_extract_are_judged_back_to_back_when_the_bench_timed_them_so(tmp_path: Path) -> None:
    """In the per-frame pipeline Head and BBox Extract follow each model's own backbone, so with the bench's
    back-to-back timing in the JSON the 0.9 - 1.1 target moves to that row; Feature Extract keeps its target."""
    dense, sparse = _bench_row("dense", 1000.0, 50.0), _bench_row("sparse", 250.0, 55.0)
    dense["back_to_back"] = {"head": {"mean_ms": 50.0, "std_ms": 0.1}, "bbox_extract": {"mean_ms": 2.0, "std_ms": 0.0}}
    sparse["back_to_back"] = {"head": {"mean_ms": 51.0, "std_ms": 0.1}, "bbox_extract": {"mean_ms": 1.9, "std_ms": 0.0}}
    (tmp_path / "bench_default.json").write_text(json.dumps({"models": [dense, sparse]}))
    rows = targets_section(tmp_path)
    assert "| sparse / dense, head time in the per-frame pipeline, allocator default | - | 1.10x |" in rows
    assert "| sparse / dense, head time back to back (same code), allocator default | 0.9 - 1.1 | 1.02x |" in rows
    bbox = "| sparse / dense, bbox_extract time back to back (same code), allocator default | 0.9 - 1.1 | 0.95x |"
    assert bbox in rows
    assert "| sparse / dense, feature_extract time (same code), allocator default | 0.9 - 1.1 | 1.00x |" in rows


def _bench_row(name: str, total: float, head: float, peer: str | None = None) -> dict:
    comps = {k: {"mean_ms": 1.0, "std_ms": 0.0} for k in ("to_device", "feature_extract", "feature_net", "backbone",
                                                          "bbox_extract")}
    comps["head"] = {"mean_ms": head, "std_ms": 0.0}
    comps["total"] = {"mean_ms": total, "std_ms": 0.0}
    return {"name": name, "peer": peer, "components": comps}


def test_bench_step_runs_the_peer_and_the_report_shows_it(tmp_path: Path, capsys) -> None:
    """The bench step asks for the Open3D-ML peer row; the targets table shows peer / ours total-time ratios and the
    shared components' sparse / dense ratios."""
    assert main(["--dry-run", "--scale", "small", "--steps", "bench", "--out", str(tmp_path / "s")]) == 0
    bench = [ln for ln in capsys.readouterr().out.splitlines() if " bench " in ln]
    assert len(bench) == 2 and all(ln.endswith("--peer open3d-ml > " + ln.split(" > ")[-1]) for ln in bench)
    assert bench[1].startswith("$ MALLOC_MMAP_MAX_=0")
    res = tmp_path / "res"
    res.mkdir()
    models = [_bench_row("dense", 1000.0, 50.0), _bench_row("sparse", 250.0, 55.0),
              _bench_row("sparse+sparse_head", 100.0, 2.0), _bench_row("open3d-ml", 1200.0, 150.0, "open3d-ml")]
    (res / "bench_default.json").write_text(json.dumps({"models": models}))
    rows = "\n".join(targets_section(res))
    peer = "| open3d-ml (Open3D-ML's dense) / "
    assert peer + "dense, total time, allocator default | >= 1 (ours no slower) | 1.20x |" in rows
    assert "| open3d-ml (Open3D-ML's dense) / sparse, total time, allocator default | - | 4.80x |" in rows
    assert "open3d-ml (Open3D-ML's dense) / sparse+sparse_head, total time" in rows
    assert "| sparse / dense, head time (same code), allocator default | 0.9 - 1.1 | 1.10x |" in rows
    assert "dense / open3d-ml" not in rows and "sparse+sparse_head / dense, head" not in rows


def test_readers_tolerate_missing_files_and_keys(tmp_path: Path) -> None:
    """The typed readers of the step outputs: a file not written (or empty) reads as None, a key a file lacks as None
    or empty, and a torn last line of metrics.jsonl is skipped."""
    from reproduction import results

    res = tmp_path / "results"
    (res / "eval_dense").mkdir(parents=True)
    (res / "eval_dense" / "metrics.json").write_text("")  # a cut write
    (res / "eval_sparse").mkdir()
    (res / "eval_sparse" / "metrics.json").write_text(json.dumps(_kitti_json(60.0, 70.0)))
    ev = results.read_eval_outputs(res)
    assert list(ev.kitti) == ["sparse"] and not ev.open3d_ml
    sparse = ev.kitti["sparse"]
    assert sparse.levels("3d", "R40") == (60.0, 61.0, 62.0) and sparse.overall("bev", "R11") == 72.5
    assert sparse.num_gt == (50, 56, 60) and sparse.num_gt_overall == 100
    assert sparse.levels("nope", "R40") is None and sparse.overall("3d", "R20") is None
    assert results.KittiMetrics.from_json({}).num_gt is None
    assert results.read_bench(res / "bench_default.json") is None and results.read_density(res / "x.json") is None
    assert results.read_manifest(tmp_path / "dataset") is None  # not generated
    write_manifest(tmp_path / "dataset", {"h0": (0, 9, {}), "h1": (10, 19, {})}, height=1.25, robot_radius=0.1)
    manifest = results.read_manifest(tmp_path / "dataset")
    assert list(manifest.houses) == ["h0", "h1"] and (manifest.sensor_height, manifest.robot_radius) == (1.25, 0.1)
    assert manifest.frames == ()
    bench = BenchResult.from_json({"models": [_bench_row("dense", 10.0, 2.0),
                                                      _bench_row("o3d", 12.0, 3.0, peer="open3d-ml")]})
    assert list(bench.ours()) == ["dense"] and list(bench.peers()) == ["o3d"]
    assert bench.ours()["dense"].mean_ms["total"] == 10.0 and not bench.ours()["dense"].back_to_back_ms
    run = _started_run(tmp_path / "w", "dense", steps=3)
    cfg = results.read_run_config(run)
    assert cfg is not None and (cfg.train.epochs, cfg.train.batch_size, cfg.train.precision) == (2, 2, "fp32")
    assert tuple(cfg.model.output_shape) == (288, 144)
    assert results.read_run_config(tmp_path / "w" / "runs" / "sparse") is None
    assert [r.step for r in results.step_records(run)] == [1, 2, 3] and results.eval_records(run) == []


def test_status_without_scale_finds_the_run_of_another_scale(tmp_path: Path, capsys, monkeypatch) -> None:
    """``tools/reproduce.py --status`` as README shows it, while a ``SCALE=small`` run is going: it shows that run
    (saying so) instead of "no reproduction here yet"; with an explicit ``--scale full`` it says which ``--scale``
    shows the run there is."""
    import reproduction.cli as reproduce_cli

    monkeypatch.setattr(reproduce_cli, "ROOT", tmp_path)
    small = tmp_path / "out" / "reproduce-small"
    small.mkdir(parents=True)
    assert reproduce_cli.main(["--status"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[:2] == ["(no --scale given and no full-scale work folder: the small-scale one)", f"{small}:"]
    assert reproduce_cli.main(["--status", "--scale", "full"]) == 0
    full = tmp_path / "out" / "reproduce-full"
    assert capsys.readouterr().out.splitlines() == [
        f"{full}: no reproduction here yet; there is one in {small} (--scale small)"]
    assert reproduce_cli.main(["--status", "--scale", "small"]) == 0
    assert capsys.readouterr().out.splitlines()[0] == f"{small}:"
