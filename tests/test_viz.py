"""``detector viz-sparsity``: the PNGs exist, have the pseudo-image size, are not blank, and sparse block 1 is no
whiter than dense block 1; ``--frame`` is the frame id (as ``mpchair view --frame``), ``--index`` the position in the
split."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers_detector import make_tiny_dataset
from PIL import Image

from detector.cli import main
from detector.viz import STAGES, viz_sparsity

SPARSE = "detector/configs/mpchair_sparse_smoke.yaml"  # 96 x 64 pseudo-image


def test_viz_sparsity_pictures(tmp_path, capsys) -> None:
    # the test split lists frames 000001 and 000002: a frame's id and its position in the split differ
    data = make_tiny_dataset(tmp_path / "ds", n_frames=3, splits={"train": [0], "val": [0], "test": [1, 2]})
    out = tmp_path / "viz"
    result = viz_sparsity(SPARSE, data, out, frame_id="000001", split="test")
    assert result["frame_id"] == "000001"
    white = {}
    for model in ("dense", "sparse"):
        for stage in STAGES:
            img = Image.open(out / f"{model}_{stage}.png")
            assert img.size == (64, 96)  # (W, H) = (nx, ny)
            a = np.asarray(img)
            assert set(np.unique(a)) <= {0, 255}
            white[model, stage] = int((a == 255).sum())
            assert white[model, stage] > 0
    assert 0 < white["dense", "input"] == white["sparse", "input"] < 64 * 96
    assert white["sparse", "block1"] <= white["dense", "block1"]
    # block-1 cells are 2x2 squares in the picture: white pixels = 4 x non-zero cells
    assert white["sparse", "block1"] == 4 * result["nonzero_cells"]["sparse"][1]
    # the input picture is the pillar set, +y up: row ny-1-iy
    assert result["nonzero_cells"]["sparse"][0] == white["sparse", "input"]
    panel = Image.open(out / "panel.png")
    assert panel.format == "PNG" and panel.size[0] > 300
    assert not list(out.glob("*.tmp*"))

    # `detector viz-sparsity`: the same pictures and numbers through the CLI (JSON, or a per-stage summary)
    with pytest.raises(SystemExit) as e:
        main(["viz-sparsity", "--config", SPARSE, "--data", str(data), "--frame", "1", "--split", "test", "--out",
              str(tmp_path / "cli"), "--json"])
    assert e.value.code == 0
    printed = json.loads(capsys.readouterr().out)
    assert {k: v for k, v in printed.items() if k != "files"} == {k: v for k, v in result.items() if k != "files"}
    assert [Path(f).name for f in printed["files"]] == [Path(f).name for f in result["files"]]
    for f in result["files"]:
        assert (tmp_path / "cli" / Path(f).name).read_bytes() == Path(f).read_bytes()
    with pytest.raises(SystemExit) as e:
        main(["viz-sparsity", "--config", SPARSE, "--data", str(data), "--frame", "1", "--split", "test", "--out",
              str(tmp_path / "cli")])
    lines = capsys.readouterr().out.splitlines()
    assert e.value.code == 0 and lines[0] == "frame 000001: non-zero fraction of the pseudo-image per stage"
    frac = result["nonzero_fraction"]["sparse"]
    assert lines[2] == "  sparse " + "  ".join(f"{s} {100 * f:.3f}%" for s, f in zip(STAGES, frac))
    assert lines[3:] == [str(f) for f in printed["files"]]

    # --frame 2 is frame 000002 (the split's second), --index 0 the split's first (000001)
    for args, fid in ((["--frame", "2"], "000002"), (["--frame", "000002"], "000002"), (["--index", "0"], "000001"),
                      (["--index", "1"], "000002")):
        with pytest.raises(SystemExit) as e:
            main(["viz-sparsity", "--config", SPARSE, "--data", str(data), *args, "--out", str(tmp_path / "pick"),
                  "--json"])
        assert e.value.code == 0 and json.loads(capsys.readouterr().out)["frame_id"] == fid, args

    split_file = data / "ImageSets" / "test.txt"
    for args, message in (
        (["--frame", "0"], f"error: {split_file}: frame 000000 is not in split 'test' (2 frames, 000001 ... 000002)"),
        (["--frame", "-1"], "error: Invalid value for '--frame': '-1' is not a frame id (up to 6 digits)"),
        (["--frame", "1234567"], "'1234567' is not a frame id"),
        (["--index", "2"], f"error: {split_file}: --index 2 is outside split 'test' (positions 0 to 1)"),
        (["--index", "-1"], "Invalid value for '--index'"),
        (["--frame", "1", "--index", "0"], "give either --frame ID (a frame id) or --index N (a position in the "
                                           "split), not both"),
    ):
        with pytest.raises(SystemExit) as e:
            main(["viz-sparsity", "--config", SPARSE, "--data", str(data), *args, "--out", str(tmp_path / "x")])
        err = capsys.readouterr().err
        assert e.value.code == 2 and message in err and len(err.splitlines()) == 1, (args, err)
        assert not (tmp_path / "x").exists()


def test_without_frame_or_index_the_frame_of_median_density_is_drawn(tmp_path, capsys) -> None:
    """The help's first example gives neither --frame nor --index: the frame drawn is the split's frame of median D
    (the split's first frame may be nearly empty), and its D is the median of the split's densities."""
    from detector.config import load_experiment, pseudoimage_geometry
    from detector.data.experiment import load_eval_frames
    from mpchair.geometry import frame_density

    data = make_tiny_dataset(tmp_path / "ds", n_frames=5, splits={"train": [0], "val": [0], "test": [0, 1, 2, 3, 4]})
    cfg = load_experiment(SPARSE)
    frames = load_eval_frames(cfg, data, "test")
    d = {f.frame_id: frame_density(f.points, pseudoimage_geometry(cfg.model))[2] for f in frames}
    assert len(set(d.values())) == 5  # distinct densities: one median frame
    median_id = sorted(d, key=d.get)[2]
    with pytest.raises(SystemExit) as e:
        main(["viz-sparsity", "--config", SPARSE, "--data", str(data), "--out", str(tmp_path / "viz"), "--json"])
    result = json.loads(capsys.readouterr().out)
    assert e.value.code == 0 and result["frame_id"] == median_id
    assert result["nonzero_fraction"]["dense"][0] == pytest.approx(d[median_id])
