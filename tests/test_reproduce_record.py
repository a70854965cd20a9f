"""The run record (reproduction/record.py): what it keeps of a work folder, restoring it, refusing a dataset that
is not the recorded one, and ``tools/reproduce.py --from-record`` writing the report of a recorded run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from helpers_detector import write_manifest, write_run_config

from mpchair.core.doctable import markers
from mpchair.core.owned import MARKER
from reproduction.checkout import ROOT
from reproduction.cli import main
from reproduction.deploy import LIKE_FOR_LIKE_DOCS, LIKE_FOR_LIKE_MARKER, like_for_like
from reproduction.record import (
    RECORD_JSON,
    RecordError,
    check_dataset,
    dataset_fingerprint,
    read_record,
    record_scale,
    restore_record,
    save_record,
)
from reproduction.report import write_report
from reproduction.scales import SCALES


def _work_folder(out: Path) -> Path:
    """A work folder with one file of every kind a reproduction leaves."""
    files = {
        "commands.log": f"    1.0 s  {ROOT}/.venv/bin/mpchair synth --out {ROOT}/out/w/houses\n",
        "results/weights.json": json.dumps({"weights": [f"{ROOT}/out/w/runs/dense/last.pt"]}),
        "results/eval_dense/metrics.json": json.dumps({"Chair": {"3d": {"overall": {"R40": 51.0}}}}),
        "results/eval_dense/data/000001.txt": "Chair 0 0 0 ...\n",
        "results/deploy_eval/dense_openvino_int8/model.onnx": "graph",
        "results/viz/panel.png": "PNG",
        "runs/dense/last.pt": "weights",
        "runs/dense/metrics.jsonl": '{"kind": "epoch", "epoch": 1, "time_s": 60.0}\n',
        "runs/dense/done": "trained\n",
        "runs/sparse_wide/metrics.jsonl": '{"kind": "step", "step": 1, "time_s": 0.1}\n',  # training, not done
        "dataset/ImageSets/val.txt": "000001\n",
        "dataset/training/velodyne/000001.bin": "points",
        "dataset/training/label_2/000001.txt": "Chair ...\n",
        "houses/v1/scans/A/house_segmentations/A.house": "house",
    }
    for rel, text in files.items():
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_text(text)
    write_run_config(out / "runs" / "dense")
    write_manifest(out / "dataset", {"A": (0, 0, {"A.house": "0" * 64})})
    return out


def test_the_record_keeps_the_reports_inputs_and_leaves_out_weights_frames_and_graphs(tmp_path: Path) -> None:
    out = _work_folder(tmp_path / "w")
    rec = tmp_path / "rec"
    assert save_record(out, rec, "full", SCALES["full"], ["a note."]) == []
    kept = sorted(str(p.relative_to(rec)) for p in rec.rglob("*") if p.is_file())
    assert kept == sorted([MARKER, RECORD_JSON, "commands.log", "results/weights.json",
                           "results/eval_dense/metrics.json", "results/viz/panel.png", "runs/dense/metrics.jsonl",
                           "runs/dense/config.yaml", "runs/dense/done", "dataset/manifest.json",
                           "dataset/ImageSets/val.txt"])
    # paths inside the checkout are relative to it (the record reads the same in any clone)
    assert (rec / "commands.log").read_text() == "    1.0 s  .venv/bin/mpchair synth --out out/w/houses\n"
    assert json.loads((rec / "results/weights.json").read_text()) == {"weights": ["out/w/runs/dense/last.pt"]}
    meta = read_record(rec)
    assert meta["notes"] == ["a note."] and meta["scale"] == "full"
    assert meta["dataset_sha256"] == dataset_fingerprint(out / "dataset") and len(meta["dataset_sha256"]) == 64
    assert record_scale(meta) == SCALES["full"]
    # a finished training keeps its done marker (a restored one is not trained again); one still running is left out
    assert (rec / "runs/dense/done").read_text() == "trained\n" and not (rec / "runs/sparse_wide").exists()
    # the accuracy study's record inside it (another command's) is carried over, never judged or dropped
    (rec / "accuracy" / "runs").mkdir(parents=True)
    (rec / "accuracy" / "record.json").write_text("{}\n")
    (rec / "accuracy" / "runs" / "last.pt").write_bytes(b"study checkpoint")
    (rec / "accuracy.json").write_text('{"splits": {}}\n')  # and the study's summary beside it
    (rec / "stream").mkdir()  # and the streaming record (tools/reproduce_stream.py's record step)
    (rec / "stream" / "record.json").write_text('{"files": []}\n')
    assert save_record(out, rec, "full", SCALES["full"], ["a note."]) == []
    assert (rec / "stream" / "record.json").read_text() == '{"files": []}\n'
    assert (rec / "accuracy" / "runs" / "last.pt").read_bytes() == b"study checkpoint"
    assert (rec / "accuracy" / "record.json").read_text() == "{}\n"
    assert (rec / "accuracy.json").read_text() == '{"splits": {}}\n'
    (rec / "stray.txt").write_text("a user's file\n")  # anything else added is still refused
    with pytest.raises(RecordError, match="stray.txt"):
        save_record(out, rec, "full", SCALES["full"], ["a note."])


def test_restore_fills_what_is_missing_and_keeps_the_dataset_out_when_it_is_regenerated(tmp_path: Path) -> None:
    out = _work_folder(tmp_path / "w")
    rec = tmp_path / "rec"
    save_record(out, rec, "full", SCALES["full"], [])
    new = tmp_path / "new"
    (new / "results/eval_dense").mkdir(parents=True)
    (new / "results/eval_dense/metrics.json").write_text("mine")
    restored = restore_record(rec, new, with_dataset=False)
    assert (new / "results/eval_dense/metrics.json").read_text() == "mine"  # never overwritten
    assert "results/weights.json" in restored and "results/eval_dense/metrics.json" not in restored
    assert not (new / "dataset").exists()  # the generate step must not find a manifest marking it done
    assert "dataset/manifest.json" in restore_record(rec, new, with_dataset=True)


def test_a_dataset_that_is_not_the_recorded_one_is_refused(tmp_path: Path) -> None:
    out = _work_folder(tmp_path / "w")
    rec = tmp_path / "rec"
    save_record(out, rec, "full", SCALES["full"], [])
    check_dataset(rec, out / "dataset")  # the same bytes: fine
    (out / "dataset/training/velodyne/000001.bin").write_text("pointz")
    with pytest.raises(RecordError, match="is not the dataset of the record"):
        check_dataset(rec, out / "dataset")


def test_a_malformed_or_escaping_record_is_refused(tmp_path: Path) -> None:
    with pytest.raises(RecordError, match="not a run record"):
        read_record(tmp_path)
    rec = tmp_path / "rec"
    rec.mkdir()
    (rec / RECORD_JSON).write_text(json.dumps({"files": ["../../etc/passwd"], "scale_sizes": {}}))
    with pytest.raises(RecordError, match="outside the record"):
        restore_record(rec, tmp_path / "new", with_dataset=True)


def test_from_record_writes_the_recorded_runs_report(tmp_path: Path, capsys) -> None:
    out = _work_folder(tmp_path / "w")
    rec = tmp_path / "rec"
    save_record(out, rec, "small", SCALES["small"], ["Recorded note."])
    report = tmp_path / "results.md"
    args = ["--from-record", str(rec), "--out", str(tmp_path / "again"), "--results", str(report)]
    assert main([*args, "--steps", "report"]) == 0
    text = report.read_text()
    assert "Recorded note." in text and "ran later" not in text  # only the report: nothing was added to the run
    assert "tools/reproduce.py --scale small" in text
    assert main([*args, "--steps", "report", "--scale", "full"]) == 2
    assert "is of a small-scale run" in capsys.readouterr().err
    assert main(["--from-record", str(tmp_path / "nothing"), "--steps", "report"]) == 2
    assert "not a run record" in capsys.readouterr().err


def test_the_committed_results_md_is_what_its_record_gives(tmp_path: Path) -> None:
    """docs/results.md and its figures are exactly the report of the committed run record (docs/results-data): a
    figure edited by hand, or a report change not written back (`tools/reproduce.py --from-record docs/results-data
    --steps report`), fails here."""
    rec = ROOT / "docs" / "results-data"
    meta = read_record(rec)
    out = tmp_path / "w"
    restore_record(rec, out, with_dataset=True)
    report = tmp_path / "docs" / "results.md"
    write_report(report, out, out / "results", meta["scale"], record_scale(meta), notes=meta["notes"])
    assert report.read_text() == (ROOT / "docs" / "results.md").read_text()
    figures = sorted(p.relative_to(report.parent) for p in (report.parent / "img").rglob("*.png"))
    assert figures, "the report of a full run has figures"
    for rel in figures:
        assert (report.parent / rel).read_bytes() == (ROOT / "docs" / rel).read_bytes(), rel
    # README and two docs lead with the record's like-for-like table (the report step writes it into each)
    table = like_for_like(out / "results")
    begin, end = markers(LIKE_FOR_LIKE_MARKER)
    for doc in LIKE_FOR_LIKE_DOCS:
        text = (ROOT / doc).read_text()
        assert table and text.split(begin, 1)[1].split(end, 1)[0] == "\n" + "\n".join(table) + "\n", doc


def test_the_opening_gives_the_fused_head_as_the_reason_only_for_a_total_ratio_above_the_papers(tmp_path: Path) -> None:
    """results.md's generated "why it differs" sentence, on the committed record: the fused dense head explains a total
    ratio above the paper's 4.6x; a total ratio below it gets no such reason."""
    from reproduction.report import why_it_differs
    from reproduction.training import trained_schedules

    out = tmp_path / "w"
    restore_record(ROOT / "docs" / "results-data", out, with_dataset=True)
    text = why_it_differs(out, out / "results", trained_schedules(out))
    assert "is above the paper's 4.6x because our dense head is fused: with the reference's" in text
    bench = out / "results" / "bench_default.json"
    d = json.loads(bench.read_text())
    for m in d["models"]:
        if m["name"] == "sparse":
            m["components"]["total"]["mean_ms"] = 1e6  # dense / sparse total far below 4.6x
    bench.write_text(json.dumps(d))
    text = why_it_differs(out, out / "results", trained_schedules(out))
    assert "is not above the paper's 4.6x: with the reference's" in text and "because our dense head" not in text
