"""The accuracy study's parts: the paired bootstrap of the AP gap, and the record a session writes, a later one
restores and continues, and the analysis reads (real tiny trainings and evaluations, not the full study)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers_detector import detector_cli, make_tiny_dataset, write_test_config

from detector.eval.bootstrap import bootstrap_gap, kitti_ap
from detector.train import train
from mpchair.kitti import Labels, read_labels
from reproduction.study import (
    Study,
    Training,
    read_zip_texts,
    record_has_test_of,
    restore,
    save,
    study_config,
    summary_path,
    trainings,
)
from reproduction.study_report import markdown, plot_curves, write_analysis


def _with_scores(labels: Labels, score: float) -> Labels:
    import dataclasses

    return dataclasses.replace(labels, score=np.full(len(labels), score))


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return make_tiny_dataset(tmp_path_factory.mktemp("tiny"), n_frames=4, seed=0)


def test_bootstrap_gap_of_a_model_that_misses_boxes(tmp_path):
    """Detections = the ground truth (score 0.9) vs the same with every other frame's boxes dropped: the gap is
    negative, its interval holds the whole-split gap and excludes 0; identical models give exactly 0 and [0, 0];
    the same seed gives the same interval."""
    data = make_tiny_dataset(tmp_path, n_frames=16, seed=3)
    ids = [f"{i:06d}" for i in range(16)]
    gt = [read_labels(data / "training" / "label_2" / f"{i}.txt") for i in ids]
    perfect = [_with_scores(g, 0.9) for g in gt]
    missing = [p if k % 2 else Labels.empty(with_score=True) for k, p in enumerate(perfect)]
    ap = kitti_ap("Chair", "3d")
    assert ap(gt, perfect) > 40.0
    g = bootstrap_gap(gt, [perfect], [missing], ap, resamples=40, seed=1)
    assert g.mean == pytest.approx(ap(gt, missing) - ap(gt, perfect))
    assert g.mean < 0 and g.ci95[0] <= g.mean <= g.ci95[1] and g.ci95[1] < 0
    assert g.ci95[1] - g.ci95[0] > 1.0  # resampling the frames spreads the gap: an interval, not a point
    assert g == bootstrap_gap(gt, [perfect], [missing], ap, resamples=40, seed=1)
    same = bootstrap_gap(gt, [perfect, perfect], [perfect], ap, resamples=10)
    assert (same.mean, same.ci95, same.seeds, len(same.pair_gaps)) == (0.0, (0.0, 0.0), (2, 1), 2)
    assert "inconclusive" in bootstrap_gap(gt, [perfect], [perfect], ap, resamples=5).verdict(0.0)
    assert "not zero" in g.verdict(10.0)
    with pytest.raises(ValueError, match="every test frame"):
        bootstrap_gap(gt, [perfect[:3]], [missing], ap)


def test_study_configs_are_the_cpu_configs_with_the_plateau_schedule():
    names = [t.name for t in trainings()]
    assert names[:6] == ["dense_s0", "sparse_s0", "dense_s1", "sparse_s1", "dense_s2", "sparse_s2"]
    assert len(names) == 10 and names[6:] == [f"{a}_s0" for a in ("sparse1_dense23", "sparse12_dense3",
                                                                    "sparse_wide", "sparse_wide_down")]
    cfg = study_config(Training("sparse", 2))
    assert cfg["train"]["schedule"] == "plateau" and cfg["train"]["seed"] == 2 and cfg["train"]["eval_every"] == 1
    assert cfg["train"]["precision"] == "fp32" and cfg["model"]["backbone"] == "sparse"
    assert cfg["model"]["output_shape"] == [288, 144]


def _tiny_plateau_config(path: Path, seed: int) -> Path:
    return write_test_config(path, train=dict(batch_size=2, epochs=30, schedule="plateau", eval_every=1,
                                              plateau_patience=1, plateau_min_delta=1000.0, plateau_decays=1,
                                              checkpoint_every=10, seed=seed))


def _train_and_test(study: Study, t: Training, data: Path, capsys, **kw) -> None:
    study.config(t).parent.mkdir(parents=True, exist_ok=True)
    config = _tiny_plateau_config(study.config(t), t.seed)
    result = train(config, data, study.run(t), threads=1, progress=False, eval_split="val", **kw)
    if result.finished:
        (study.run(t) / "done").write_text("trained\n")
        code, out, err = detector_cli(["eval", "--config", config, "--data", data, "--checkpoint",
                                       study.run(t) / "last.pt", "--split", "test", "--out", study.test(t),
                                       "--threads", "1"], capsys)
        assert code == 0, out + err


def test_the_record_accumulates_across_sessions_and_feeds_the_analysis(data, tmp_path, capsys):
    """Session 1 finishes dense_s0 and sparse_s0 and cuts dense_s1; its record holds the summaries, the test
    detections and dense_s1's last.pt. Session 2 restores it into a new work folder, finishes dense_s1 from the
    restored checkpoint, and its record drops that last.pt. The analysis then has curves, test AP and a gap."""
    record = tmp_path / "record"
    (record / "notes.txt").parent.mkdir(parents=True)
    (record / "notes.txt").write_text("a file of someone else\n")
    one = Study(out=tmp_path / "one", record=record)
    shutil.copytree(data, one.data)
    dense0, sparse0, dense1 = Training("dense", 0), Training("sparse", 0), Training("dense", 1)
    _train_and_test(one, dense0, one.data, capsys)
    _train_and_test(one, sparse0, one.data, capsys)
    _train_and_test(one, dense1, one.data, capsys, max_steps=3)
    _train_and_test(one, Training("sparse", 1), one.data, capsys, max_steps=1)  # cut inside its first epoch
    save(one, fingerprint="abc", notes=("ran here",))
    meta = json.loads((record / "record.json").read_text())
    assert "sparse_s1" not in meta["trainings"] and not (record / "runs" / "sparse_s1").exists()
    assert meta["notes"] == ["ran here"]
    assert meta["trainings"]["dense_s0"] == {"status": "done", "model": "dense", "seed": 0, "tested": True}
    assert meta["trainings"]["dense_s1"]["status"] == "partial" and meta["dataset_sha256"] == "abc"
    assert (record / "runs" / "dense_s1" / "last.pt").is_file()
    assert not (record / "runs" / "dense_s0" / "last.pt").exists()
    kinds = {json.loads(x)["kind"] for x in (record / "runs" / "dense_s0" / "metrics.jsonl").read_text().splitlines()}
    assert kinds == {"epoch", "eval", "end"}  # no per-step records in the record
    assert sorted(read_zip_texts(record / "test" / "sparse_s0" / "detections.zip")) == [f"{i:06d}" for i in range(4)]
    assert (record / "notes.txt").read_text() == "a file of someone else\n"

    two = Study(out=tmp_path / "two", record=record)
    shutil.copytree(data, two.data)
    assert sorted(restore(two)) == ["dense_s0", "dense_s1", "sparse_s0"]
    # dense_s0 comes back done but without last.pt or test files: the test step must not evaluate it again
    assert two.done(dense0) and not two.tested(dense0) and not (two.run(dense0) / "last.pt").exists()
    assert record_has_test_of(two, dense0) and record_has_test_of(two, sparse0) and not record_has_test_of(two, dense1)
    assert (two.run(dense1) / "last.pt").read_bytes() == (record / "runs" / "dense_s1" / "last.pt").read_bytes()
    step = torch.load(two.run(dense1) / "last.pt", weights_only=True)["step"]
    assert step == 3
    _train_and_test(two, dense1, two.data, capsys, resume=True)
    assert two.done(dense1)
    save(two, fingerprint=None)
    assert not (record / "runs" / "dense_s1" / "last.pt").exists()
    assert json.loads((record / "record.json").read_text())["dataset_sha256"] == "abc"

    data_out = write_analysis(record, resamples=20)
    by = {t["name"]: t for t in data_out["trainings"]}
    assert set(by) == {"dense_s0", "sparse_s0", "dense_s1"}
    assert by["dense_s0"]["val_epochs"] == [1, 2, 3] and by["dense_s0"]["ended_by"] == "plateau"
    assert len(by["dense_s0"]["val_ap_3d"]) == 3 and "ap_3d" in by["dense_s0"]["test"]
    gap = data_out["gap_3d"]
    assert gap["seeds"] == {"a": 2, "b": 1} and gap["ci95"][0] <= gap["ci95"][1]
    dense_mean = np.mean([by[n]["test"]["ap_3d"] for n in ("dense_s0", "dense_s1")])
    assert gap["mean"] == pytest.approx(by["sparse_s0"]["test"]["ap_3d"] - dense_mean)
    assert summary_path(record) == tmp_path / "record.json"  # beside the record folder, named after it
    saved = json.loads(summary_path(record).read_text())
    assert not (record / "accuracy.json").exists()  # one summary, not a copy in the record too
    assert saved["gap_3d"]["mean"] == pytest.approx(gap["mean"])
    from reproduction.study_report import analyse

    assert analyse(record, resamples=20) == saved  # the same tested seeds: the gaps come back, not redrawn
    assert analyse(record, resamples=21)["gap_3d"]["resamples"] == 21  # other settings: drawn again
    md = (record / "accuracy.md").read_text()
    assert md == markdown(saved) and f"{gap['mean']:+.2f}" in md and "Note: ran here" in md
    png = (record / "curves.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    write_analysis(record, resamples=20)
    assert (record / "curves.png").read_bytes() == png  # same record, same bytes


def _eval_line(epoch: int, ap_3d: float, ap_bev: float) -> str:
    overall = {k: {"overall": {"R40": v, "R11": v}} for k, v in (("3d", ap_3d), ("bev", ap_bev))}
    return json.dumps({"kind": "eval", "epoch": epoch, "split": "val", "Chair": overall}) + "\n"


def test_the_summary_has_every_key_before_any_test_and_the_curves_show_3d_and_bev(tmp_path):
    """A record with validation curves only (nothing tested yet): the summary still holds splits, trainings (test AP
    null) and gap_3d / gap_bev with null mean and ci95; accuracy.md says the gap is not measured; curves.png has the
    3D and the BEV panel side by side and the same bytes when written again."""
    record = tmp_path / "accuracy"
    curves = {"dense_s0": [(30.0, 33.0), (40.0, 44.0), (42.0, 45.5)], "dense_s1": [(28.0, 31.0), (39.0, 41.0)],
              "sparse_s0": [(25.0, 27.0)]}
    for name, points in curves.items():
        (record / "runs" / name).mkdir(parents=True)
        (record / "runs" / name / "metrics.jsonl").write_text(
            "".join(_eval_line(e, a, b) for e, (a, b) in enumerate(points, 1)))
    splits = {"train": ["h0", "h1"], "val": ["h2"], "test": ["h3"]}
    states = {n: {"status": "partial", "model": n.split("_")[0], "seed": int(n[-1])} for n in curves}
    (record / "record.json").write_text(json.dumps({"split_houses": splits, "trainings": states}))
    data = write_analysis(record)
    saved = json.loads((tmp_path / "accuracy.json").read_text())
    assert saved == data and saved["splits"] == splits
    by = {t["name"]: t for t in saved["trainings"]}
    assert [t["name"] for t in saved["trainings"]] == ["dense_s0", "sparse_s0", "dense_s1"]  # the study's order
    assert by["dense_s0"]["val_ap_3d"] == [30.0, 40.0, 42.0] and by["dense_s0"]["val_ap_bev"] == [33.0, 44.0, 45.5]
    assert (by["dense_s1"]["model"], by["dense_s1"]["seed"], by["dense_s1"]["epochs"]) == ("dense", 1, 2)
    assert all(t["test"] is None for t in saved["trainings"])
    for key in ("gap_3d", "gap_bev"):
        assert saved[key]["mean"] is None and saved[key]["ci95"] is None
    assert "Sparse - dense gap: not measured yet" in (record / "accuracy.md").read_text()
    png = (record / "curves.png").read_bytes()
    width, height = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
    assert width > 2 * height  # two panels side by side
    plot_curves(saved, tmp_path / "again.png")
    assert (tmp_path / "again.png").read_bytes() == png


ROOT = Path(__file__).resolve().parents[1]


def test_the_committed_accuracy_record_agrees_with_its_analysis_and_results_md():
    """docs/results-data/accuracy: its summary docs/results-data/accuracy.json is the analysis of the record's files
    (the curves, states and test AP; a gap's bootstrap is reused while its tested trainings are the same, and checked
    by its own tests), accuracy.md is written from it, and docs/results.md shows that text."""
    from reproduction.study_report import analyse

    record = ROOT / "docs" / "results-data" / "accuracy"
    saved = json.loads((ROOT / "docs" / "results-data" / "accuracy.json").read_text())
    assert not (record / "accuracy.json").exists()  # the summary lives beside the record, once
    fresh = analyse(record)  # the gaps, when there are any, come back from accuracy.json unless their inputs changed
    assert fresh == saved
    assert set(saved["splits"]) == {"train", "val", "test"} and len(saved["splits"]["test"]) >= 2
    assert len(saved["splits"]["val"]) >= 2 and not set(saved["splits"]["test"]) & set(saved["splits"]["train"])
    for t in saved["trainings"]:
        assert t["val_epochs"] == list(range(1, len(t["val_ap_3d"]) + 1)) and t["epochs"] == len(t["val_ap_3d"])
    assert (record / "accuracy.md").read_text() == markdown(saved)
    assert (record / "accuracy.md").read_text().strip() in (ROOT / "docs" / "results.md").read_text()


def _accuracy_section(results_md: str) -> str:
    start = results_md.index("\n## Accuracy")
    end = results_md.find("\n## ", start + 1)
    return results_md[start:end if end > 0 else None]


def test_results_md_prints_the_figures_of_accuracy_json():
    """docs/results.md's Accuracy section and docs/results-data/accuracy.json give the same figures: the counts of
    trainings, the houses of each split, each training's row (status, epochs, best val 3D AP, test 3D / BEV AP) and
    the gap (its mean and interval, or that it is not measured). Read from the text, not through the code that wrote
    it."""
    import re

    summary = json.loads((ROOT / "docs" / "results-data" / "accuracy.json").read_text())
    section = _accuracy_section((ROOT / "docs" / "results.md").read_text())
    for key in ("splits", "trainings", "gap_3d"):
        assert key in summary, key
    assert {"mean", "ci95"} <= set(summary["gap_3d"])
    trainings = summary["trainings"]
    done = sum(t["status"] == "done" for t in trainings)
    assert f"Trainings in the record: {len(trainings)} of 10 started, {done} finished" in section
    houses = re.search(r"Houses per split: (.*)\.\n", section).group(1)
    assert dict(part.split(" ", 1) for part in houses.split("; ")) == {
        k: ", ".join(v) for k, v in summary["splits"].items()}
    rows = {m.group(1): m.group(2).split(" | ")
            for m in re.finditer(r"^\| (\w+_s\d) \| (.*) \|$", section, flags=re.MULTILINE)}
    assert sorted(rows) == sorted(t["name"] for t in trainings)

    def fmt(x):
        return "–" if x is None else f"{x:.2f}"

    for t in trainings:
        status, epochs, best, _ended, test_3d, test_bev = rows[t["name"]]
        test = t["test"] or {}
        assert (status, int(epochs)) == (t["status"], t["epochs"]) and len(t["val_ap_3d"]) == t["epochs"]
        assert (best, test_3d, test_bev) == (fmt(max(t["val_ap_3d"], default=None)), fmt(test.get("ap_3d")),
                                             fmt(test.get("ap_bev"))), t["name"]
    gap = summary["gap_3d"]
    if gap["mean"] is None:
        assert gap["ci95"] is None and "Sparse - dense gap: not measured yet" in section
    else:
        lo, hi = gap["ci95"]
        assert lo <= gap["mean"] <= hi
        assert (f"3D AP (KITTI Overall R40): {gap['mean']:+.2f}, 95 % interval [{lo:+.2f}, {hi:+.2f}]"
                in section)
