"""The paper's published figures live in ``mpchair/paper.py`` only: the table agrees with the paper's LaTeX where it is
vendored, and no module of either package nor a tool writes one of its figures again."""

from __future__ import annotations

import json
import re
from dataclasses import fields, is_dataclass
from pathlib import Path

import pytest

from mpchair import paper
from mpchair.analysis.stats import PAPER_DENSITY

ROOT = Path(__file__).resolve().parents[1]
TEX = Path("/work/shared/paper/sparse-pointpillars.tex")


def _numbers(value: object) -> list[float]:
    """Every float of a table entry (dataclasses and mappings walked)."""
    if isinstance(value, float):
        return [value]
    if is_dataclass(value):
        return [x for f in fields(value) for x in _numbers(getattr(value, f.name))]
    if hasattr(value, "values"):
        return [x for v in value.values() for x in _numbers(v)]
    return []


#: Table numbers too common to mark a copy: 1.25 (the paper's "25 % more epochs" as a ratio) is also the released
#: code's sensor height in metres and the recipe's sparse / dense epoch ratio.
COMMON = {1.25}


#: Lines that hold one of the figures by coincidence (another measurement), by file and figure.
COINCIDENCES = {("detector/train/loop.py", 4.98)}  # a measured 4.98 ms per optimizer step, not Table III's -4.98


def figures() -> list[float]:
    """The table's figures a copy would be recognised by: every number with at least three significant digits (the
    short ones, like 1.8 or a std of 0.001, would match unrelated code), but :data:`COMMON`."""
    out = set()
    for name in dir(paper):
        if name.isupper():
            out.update(abs(x) for x in _numbers(getattr(paper, name)))
    return sorted(x for x in out - COMMON if len(repr(x).replace(".", "").lstrip("0")) >= 3)


def _pattern(x: float) -> re.Pattern:
    # 14.41 also matches "14.410", 0.0246 does not match "0.02459"; a digit or point on either side is another number
    return re.compile(r"(?<![\d.])" + re.escape(repr(x)) + r"0*(?![\d])")


def test_the_figures_are_the_papers():
    """Spot checks of each kind of entry against the printed paper (section IV, V-A, Tables II-IV)."""
    assert paper.MATTERPORT_CHAIR_DENSITY == paper.Density(median=0.0075, min=0.00029, max=0.01679)
    assert paper.KITTI_DENSITY.median == 0.02459
    assert paper.MATTERPORT_CHAIR_AP.sparse_3d_delta == -4.61
    assert paper.TABLE_II["robot"]["sparse"].total == paper.Timed(236.737, 2.491)
    assert paper.TABLE_II["robot"]["dense"].backbone.mean_ms == 879.225
    assert paper.TABLE_III["sparse_wide_down"].ap_3d.moderate == -11.57
    assert paper.TABLE_IV["sparse12_dense3"].total.mean_ms == 15.001
    # a row's components are the paper's columns, in its order
    assert [n for n, _ in paper.TABLE_IV["dense"].items()] == [
        "to_device", "feature_extract", "feature_net", "backbone", "head", "bbox_extract", "total"]


@pytest.mark.skipif(not TEX.exists(), reason="the paper's LaTeX is not vendored here")
def test_every_figure_is_printed_in_the_paper():
    """Each scanned figure appears in the LaTeX source (thousands separators removed, trailing zeros allowed)."""
    tex = TEX.read_text(encoding="utf-8").replace("1,082", "1082")
    missing = [x for x in figures() if not _pattern(x).search(tex)]
    assert not missing, missing


def test_no_figure_is_copied_outside_the_table():
    """A paper figure written as a literal anywhere in mpchair/, detector/, reproduction/ or tools/ (code, string or
    comment) other than mpchair/paper.py fails; import it from ``mpchair.paper`` instead."""
    patterns = {x: _pattern(x) for x in figures()}
    assert len(patterns) > 100  # the scan covers Tables II-IV, not only the headline numbers
    bad = []
    files = [*ROOT.joinpath("mpchair").rglob("*.py"), *ROOT.joinpath("detector").rglob("*.py"),
             *ROOT.joinpath("reproduction").rglob("*.py"), *ROOT.joinpath("tools").glob("*.py")]
    for path in files:
        if path == ROOT / "mpchair" / "paper.py":
            continue
        for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            rel = path.relative_to(ROOT).as_posix()
            bad += [f"{rel}:{i}: {x}" for x, p in patterns.items() if p.search(line) and (rel, x) not in COINCIDENCES]
    assert not bad, "\n".join(bad)


def test_the_scan_catches_a_copy():
    """The scanner can fail: the headline figures, written the ways the reports used to, are found."""
    hits = {x for x in figures() for text in ("total 236.737 ms", "D = 0.02459", "(paper -4.61)", "0.00750, 0.01679")
            if _pattern(x).search(text)}
    assert {236.737, 0.02459, 4.61, 0.01679} <= hits
    assert not _pattern(0.0246).search("0.02459") and not _pattern(236.737).search("1236.7371")


def test_stats_json_keeps_its_paper_entries():
    """``mpchair stats --json``'s ``paper`` object is unchanged by the move (same keys, order and values)."""
    assert json.dumps(PAPER_DENSITY) == (
        '{"matterport_chair": {"median": 0.0075, "min": 0.00029, "max": 0.01679}, '
        '"kitti": {"median": 0.02459, "min": 0.013321, "max": 0.03899}}')
