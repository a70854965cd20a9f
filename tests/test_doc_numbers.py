"""The numbers docs/stats.md quotes are the ones its script (tools/doc_pictures.py, a front-end of
``reproduction.doc_pictures``) gets from the code today: the script makes them again (``--check``: no pictures) and
each marked block of the page must equal what it would write."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import reproduction.doc_pictures

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "stats.md"


@pytest.fixture(scope="module")
def tool():
    return reproduction.doc_pictures


@pytest.fixture(scope="module")
def checked(tool, tmp_path_factory) -> dict:
    """``doc_pictures.py --check`` (its defaults: the commands the page quotes) on a copy of the page whose boxes block
    is stale; then every block's text as the script makes it, from the numbers that run measured."""
    base = tmp_path_factory.mktemp("doc-numbers")
    page = base / "stats.md"
    stale = tool.fill_blocks(DOC.read_text(encoding="utf-8"), {"boxes": "* chairs: 0 boxes"}, DOC)
    page.write_text(stale, encoding="utf-8")
    code = tool.main(["--check", "--doc", str(page), "--work", str(base / "work")])
    measured = json.loads((base / "work" / "measured.json").read_text())
    return {"code": code, "page": page, "stale": stale, "blocks": tool.number_blocks(measured, tool.parse_args([]))}


@pytest.mark.slow
def test_docs_stats_numbers_are_current(tool, checked):
    text, blocks = DOC.read_text(encoding="utf-8"), checked["blocks"]
    stale = [name for name in blocks if tool.fill_blocks(text, {name: blocks[name]}, DOC) != text]
    assert not stale, f"docs/stats.md blocks {stale} are stale: run python tools/doc_pictures.py"
    assert "points per box: median " in blocks["boxes"] and "| 000005 |" in blocks["kitti-density"]


@pytest.mark.slow
def test_check_fails_on_a_stale_number_and_the_script_writes_the_current_one(tool, checked):
    assert checked["code"] == 1 and checked["page"].read_text(encoding="utf-8") == checked["stale"]  # untouched
    text, blocks = DOC.read_text(encoding="utf-8"), checked["blocks"]
    quoted = blocks["boxes"].split("points per box: median ")[1].split(" ")[0]
    # The median of an even number of boxes can be a half (e.g. 191.5): bump its integer part.
    stale = text.replace(f"points per box: median {quoted} ", f"points per box: median {int(float(quoted)) + 2} ")
    assert stale != text and tool.fill_blocks(stale, blocks, DOC) == text
    begin, _ = tool.markers("boxes")
    with pytest.raises(tool.CommandError, match="expected one '<!-- doc_pictures.py boxes: begin -->' line"):
        tool.fill_blocks(text.replace(begin, ""), blocks, DOC)
