"""The realism calibration (``mpchair.analysis.calibration``, ``tools/realism_calibration.py``): its numbers are the
datasets' own (checked against ``mpchair stats`` and the manifest), the table lands between the doc's markers, and
the hole picture shows a box that ``in_box_fraction`` rejected."""

from __future__ import annotations

import dataclasses
from collections import Counter

import numpy as np
import pytest
from PIL import Image

from mpchair.analysis.calibration import (
    BEGIN,
    END,
    ORIGINAL,
    REASONS,
    CalibrationPlan,
    calibrate,
    dataset_of,
    find_hole_frame,
    format_table,
    hole_picture,
    markers,
    target_misses,
    write_doc_table,
)
from mpchair.analysis.stats import box_stats, density_stats
from mpchair.core.errors import InputError
from mpchair.dataset.manifest import read_manifest


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    plan = CalibrationPlan(work=tmp_path_factory.mktemp("calib"), seeds=(1,), houses=1, frames=30)
    return plan, calibrate(plan)


def test_rows_are_the_datasets_own_numbers(calibrated):
    plan, rows = calibrated
    assert [r["label"] for r in rows] == ["synthetic clean, seed 1", "synthetic clean, all 1 seeds",
                                          "synthetic default, seed 1", "synthetic default, all 1 seeds"]
    for preset, row in (("clean", rows[0]), ("default", rows[2])):
        data = dataset_of(plan, preset, 1)
        dens = density_stats(data)
        assert row["frames"] == 30 and row["d_median"] == pytest.approx(dens["median"])
        assert row["d_max"] == pytest.approx(dens["max"])
        boxes = box_stats(data, classes=["Chair"])
        assert row["kept"] == boxes["classes"]["Chair"]["count"]
        assert row["mean_lwh"] == pytest.approx(boxes["classes"]["Chair"]["anchor_lwh"])
        counts = Counter(b.reason for f in read_manifest(data).frames for b in f.rejected)
        assert row["rejected"] == {r: counts.get(r, 0) for r in REASONS}
    # what the realism changes: the clean house never rejects for holes, the default one does
    assert rows[0]["rejected"]["in_box_fraction"] == 0 and rows[2]["rejected"]["in_box_fraction"] > 0
    assert rows[2]["d_median"] > rows[0]["d_median"]


def test_the_table_lands_between_the_markers(calibrated, tmp_path):
    plan, rows = calibrated
    table = format_table(rows, plan)
    lines = [ln for ln in table.splitlines() if ln.startswith("|")]
    assert len(lines) == 2 + 2 + len(rows)  # header, rule, original, target, rows
    assert all(ln.count("|") == lines[0].count("|") == 17 for ln in lines)  # with the targets column
    assert "tools/realism_calibration.py --seeds 1 --houses 1 --frames 30" in table
    doc = tmp_path / "doc.md"
    doc.write_text(f"before\n{BEGIN}\nold table\n{END}\nafter\n")
    write_doc_table(doc, table)
    text = doc.read_text()
    assert text.startswith(f"before\n{BEGIN}\n") and text.endswith(f"{END}\nafter\n") and "old table" not in text
    assert table in text
    doc.write_text("no markers\n")
    with pytest.raises(InputError, match="markers"):
        write_doc_table(doc, table)
    # Each row says which of issue 27's targets it misses (the clean house: the two visibility filters never fire).
    assert "misses D median, D max, `points_in_box`, `in_box_fraction`" in lines[4]


def test_another_height_has_its_own_markers_and_no_targets(calibrated, tmp_path):
    plan, rows = calibrated
    table = format_table(rows, dataclasses.replace(plan, height=1.0))
    lines = [ln for ln in table.splitlines() if ln.startswith("|")]
    assert len(lines) == 2 + 1 + len(rows) and "target" not in table and "--height 1 " in table
    assert all(ln.count("|") == lines[0].count("|") == 16 for ln in lines)
    begin, end = markers("calibration-table-1m")
    doc = tmp_path / "doc.md"
    doc.write_text(f"{BEGIN}\nmain\n{END}\n{begin}\nold\n{end}\n")
    write_doc_table(doc, table, "calibration-table-1m")
    assert doc.read_text() == f"{BEGIN}\nmain\n{END}\n{begin}\n{table}{end}\n"


def test_target_misses_names_each_missed_target(calibrated):
    _, rows = calibrated
    row = rows[2] | {"d_median": 0.0075, "d_max": 0.014, "mean_lwh": list(ORIGINAL["lwh"]), "kept": 100,
                     "rejected": rows[2]["rejected"] | {"points_in_box": 2, "in_box_fraction": 2}}
    assert target_misses(row) == []
    assert target_misses(row | {"d_median": 0.0067, "d_max": 0.0129}) == [
        "D median 0.00670 outside 0.00675-0.00825", "D max 0.01290 < 0.013"]
    assert target_misses(row | {"rejected": row["rejected"] | {"in_box_fraction": 1}}) == [
        "in_box_fraction rejected 1 < 2% of 100 kept"]
    assert target_misses(row | {"mean_lwh": [1.01, 0.667, 0.83]}) == [
        "mean chair l 1.010 m is +5.2 % off 0.960 m", "mean chair h 0.830 m is -6.1 % off 0.884 m"]
    assert target_misses(row | {"mean_lwh": None}) == ["no chair box kept"]


#: The seeds every default-realism dataset of the doc's size (8 houses x 40 frames) must meet issue 27's targets on.
TEST_SEEDS = (0, 1, 2, 3, 4, 5)


@pytest.mark.slow
def test_default_realism_meets_the_targets_on_every_test_seed(tmp_path):
    # The doc table's setting (tools/realism_calibration.py --houses 8 --frames 40), default realism only: about 40 s
    # of CPU per seed. Every seed by itself, not only their pool: a dataset made from any seed must look like MP3D's.
    plan = CalibrationPlan(work=tmp_path, presets=("default",), seeds=TEST_SEEDS, houses=8, frames=40)
    rows = [r for r in calibrate(plan) if not r.get("pooled")]
    assert len(rows) == len(TEST_SEEDS)
    assert {r["label"]: target_misses(r) for r in rows} == {r["label"]: [] for r in rows}


def test_the_hole_picture_shows_a_rejected_box(calibrated, tmp_path):
    plan, _ = calibrated
    data = dataset_of(plan, "default", 1)
    record, box = find_hole_frame(data)
    fid = record.frame
    assert box.reason == "in_box_fraction" and box in record.rejected
    assert record in read_manifest(data).frames
    info = hole_picture(data, data.parent / "houses", tmp_path / "hole.png")
    assert info["frame"] == fid
    with Image.open(tmp_path / "hole.png") as im:
        rgb = np.asarray(im.convert("RGB"))
    red = (rgb[..., 0] > 200) & (rgb[..., 1] < 80) & (rgb[..., 2] < 80)
    assert red.sum() > 50  # the dashed rejected box is drawn
    with pytest.raises(InputError, match="no box was rejected for in_box_fraction"):
        hole_picture(dataset_of(plan, "clean", 1), data.parent / "houses", tmp_path / "none.png")
