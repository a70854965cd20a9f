"""``mpchair synth`` and ``mpchair houses`` through ``mpchair.cli.main``: JSON numbers equal the construction."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from mpchair.cli import main
from mpchair.synth import plan_houses, synthesize_house

SEED = 23


def _run(args: list[str], capsys) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as e:
        main(args)
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


@pytest.fixture(scope="module")
def synth_root(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("cli")


def test_synth_then_houses_json_matches_construction(synth_root: Path, capsys) -> None:
    code, out, _ = _run(["synth", "--out", str(synth_root), "--houses", "1", "--seed", str(SEED), "--json"], capsys)
    assert code == 0
    plan = plan_houses(1, SEED)
    assert json.loads(out) == {"root": str(synth_root), "houses": [p[0] for p in plan]}

    code, out, _ = _run(["houses", "--root", str(synth_root), "--json"], capsys)
    assert code == 0
    rows = json.loads(out)["houses"]
    assert [r["id"] for r in rows] == sorted(p[0] for p in plan)
    by_id = {r["id"]: r for r in rows}
    for hid, hs, lv in plan:
        syn = synthesize_house(hs, hid, levels=lv)
        r = by_id[hid]
        counts: dict[str, int] = {}
        for o in syn.objects:
            counts[o.mpcat40_name] = counts.get(o.mpcat40_name, 0) + 1
        assert (r["levels"], r["regions"], r["objects"]) == (lv, len(syn.house_file.regions), len(syn.objects))
        assert (r["faces"], r["vertices"]) == (len(syn.faces), len(syn.vertices))
        assert r["unlabelled_faces"] == syn.unlabelled_faces
        assert r["objects_by_category"] == dict(sorted(counts.items()))
        assert r["label_mismatch_rate"] == pytest.approx(syn.mismatched_faces / len(syn.faces))

    code, out, _ = _run(["houses", "--root", str(synth_root)], capsys)
    assert code == 0 and all(f"{p[0]} (release): ASCII 1.1, {p[2]} levels" in out for p in plan)


def test_houses_objects_lists_chair_boxes(synth_root: Path, capsys) -> None:
    hid, hs, lv = plan_houses(1, SEED)[0]
    if not (synth_root / "v1").exists():
        _run(["synth", "--out", str(synth_root), "--houses", "1", "--seed", str(SEED)], capsys)
    code, out, _ = _run(["houses", "--root", str(synth_root), "--house", hid, "--objects", "--category", "chair",
                         "--json"], capsys)  # fmt: skip
    assert code == 0
    got = json.loads(out)
    syn = synthesize_house(hs, hid, levels=lv)
    chairs = [o for o in syn.objects if o.mpcat40_index == 3]
    assert got["id"] == hid and [o["index"] for o in got["objects"]] == [o.index for o in chairs]
    assert {o["mpcat40_name"] for o in got["objects"]} == {"chair"}
    boxes = np.array([o["aligned_box"] for o in got["objects"]])
    truth = np.stack([o.aligned_box for o in chairs])
    np.testing.assert_allclose(boxes[:, :6], truth[:, :6], atol=1e-5)
    np.testing.assert_allclose((boxes[:, 6] - truth[:, 6] + math.pi / 2) % math.pi - math.pi / 2, 0, atol=1e-5)
    code, out, _ = _run(["houses", "--root", str(synth_root), "--house", hid, "--objects", "--category", "19"],
                        capsys)  # fmt: skip
    assert code == 0 and out.splitlines()[0] == f"{hid}: {sum(o.mpcat40_index == 19 for o in syn.objects)} objects"


def test_synth_zip_layout_is_read_by_houses(tmp_path: Path, capsys) -> None:
    code, out, _ = _run(["synth", "--out", str(tmp_path), "--houses", "1", "--seed", "4", "--zip"], capsys)
    assert code == 0
    hid = out.strip()
    assert (tmp_path / "v1" / "scans" / hid / "house_segmentations.zip").is_file()
    code, out, _ = _run(["houses", "--root", str(tmp_path / "v1" / "scans" / hid), "--json"], capsys)
    assert code == 0 and [r["id"] for r in json.loads(out)["houses"]] == [hid]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["houses", "--root", "{tmp}/nowhere"], "error: {tmp}/nowhere: house root not found"),
        (["houses", "--root", "{data}", "--house", "NOPE"], "error: {data}: house 'NOPE' not found (found: "),
        (["houses", "--root", "{data}", "--house", "MINI0000011", "--objects", "--category", "throne"],
         "error: unknown mpcat40 class 'throne'"),
        (["houses", "--root", "{data}", "--objects"], "Error: --objects needs --house ID"),
    ],
)  # fmt: skip
def test_bad_cli_input_exits_2_with_one_line(tmp_path: Path, capsys, args: list[str], message: str) -> None:
    data = str(Path(__file__).parent / "data" / "matterport")
    args = [a.format(tmp=tmp_path, data=data) for a in args]
    code, out, err = _run(args, capsys)
    assert code == 2 and out == ""
    assert message.format(tmp=tmp_path, data=data) in err and "Traceback" not in err
    if message.startswith("error:"):
        assert err.count("\n") == 1
