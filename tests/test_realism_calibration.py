"""The realism calibration (``mpchair.analysis.calibration``, ``tools/realism_calibration.py``): its numbers are the
datasets' own (checked against ``mpchair stats`` and the manifest), the table lands between the doc's markers, and
the hole picture shows a box that ``in_box_fraction`` rejected."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
from PIL import Image

from mpchair.analysis.calibration import (
    BEGIN,
    END,
    REASONS,
    CalibrationPlan,
    calibrate,
    dataset_of,
    find_hole_frame,
    format_table,
    hole_picture,
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
    assert all(ln.count("|") == lines[0].count("|") for ln in lines)
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
