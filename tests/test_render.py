"""Pictures render headless: ``mpchair view`` (bird's-eye view, detections, 3D) and ``mpchair view-house``; PNGs have
the asked size, are not blank and show what they claim (ground truth green, detections red, chairs orange)."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image
from test_stats import KITTI, build_small_dataset, independent_density, run_main, small_calib

from mpchair.analysis.render import render_house
from mpchair.analysis.stats import MATTERPORT_GEOMETRY
from mpchair.cli import cli
from mpchair.dataset.generate import GenerateRequest, generate
from mpchair.geometry import boxes_to_kitti_camera
from mpchair.kitti import Labels, read_velodyne, write_labels
from mpchair.synth import write_synthetic_houses


def run(*args) -> tuple[int, str]:
    result = CliRunner().invoke(cli, [str(a) for a in args])
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise result.exception
    return result.exit_code, result.output


def rgb(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB")).astype(np.int64)


def near(image: np.ndarray, colour: str, tol: int = 40) -> int:
    """Pixels within ``tol`` (per channel) of a ``#rrggbb`` colour."""
    target = np.array([int(colour[i:i + 2], 16) for i in (1, 3, 5)])
    return int(np.all(np.abs(image - target) <= tol, axis=-1).sum())


def assert_picture(path: Path, size: tuple[int, int], min_colours: int = 20) -> np.ndarray:
    image = rgb(path)
    assert image.shape == (size[1], size[0], 3)
    assert image.std() > 15
    assert len(np.unique(image.reshape(-1, 3), axis=0)) >= min_colours
    return image


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    return build_small_dataset(tmp_path_factory.mktemp("small_render"))


def test_view_bev_with_detections(small, tmp_path):
    # Results: the frame's first box shifted 0.3 m (16 columns, with a score), written like a detector would.
    results = tmp_path / "results"
    box = np.array([[3.3, 1.0, -0.6, 0.9, 0.6, 0.9, 0.3]])
    loc, dims, ry, alpha = boxes_to_kitti_camera(box, small_calib())
    write_labels(results / "000000.txt", Labels(["Chair"], [-1], [-1], alpha, [[0, 0, 50, 50]], dims, loc, ry,
                                                score=[0.87]))
    plain, with_dets = tmp_path / "plain.png", tmp_path / "dets.png"
    code, out = run("view", small, "--frame", "0", "--out", plain, "--size", "640", "480")
    assert code == 0, out
    code, out = run("view", small, "--frame", "000000", "--out", with_dets, "--results", results, "--size", "640",
                    "480", "--json")
    assert code == 0, out
    info = json.loads(out)
    assert (info["boxes"], info["detections"], info["out_3d"]) == (2, 1, None)
    a, b = assert_picture(plain, (640, 480)), assert_picture(with_dets, (640, 480))
    assert near(a, "#00b050") > 100 and near(b, "#00b050") > 100  # ground truth outlines
    assert near(a, "#e8242b") < 5 < 40 < near(b, "#e8242b")  # the detection (and its score) appear only with it


def test_view_bad_inputs(small, tmp_path, capsys):
    code, out = run_main(capsys, "view", small, "--frame", "7", "--out", tmp_path / "x.png")
    assert code == 2 and out.startswith("error: ") and "frame 000007 not found" in out
    code, out = run_main(capsys, "view", small, "--frame", "0", "--out", tmp_path / "x.png", "--results",
                         tmp_path / "none")
    assert code == 2 and out.count("\n") == 1 and f"{tmp_path / 'none'}: result folder not found" in out
    # a frame outside the results' split: said as a result file, not a "label file"
    (tmp_path / "res").mkdir()
    code, out = run_main(capsys, "view", small, "--frame", "0", "--out", tmp_path / "x.png", "--results",
                         tmp_path / "res")
    assert code == 2 and out.count("\n") == 1 and "label file" not in out
    assert "res/000000.txt: result file not found: frame 000000 is not among these results" in out
    assert not (tmp_path / "x.png").exists()


def test_view_cuts_the_ceiling_by_default(small, tmp_path):
    """On an mpchair dataset the default --zmax is 2.0 m above the floor (2.0 - the manifest's sensor height): the
    points at or above it are left out of the picture; --zmax none keeps them; a folder without a manifest (real
    KITTI) keeps every point by default."""
    ds = tmp_path / "ds"
    shutil.copytree(small, ds)
    manifest = json.loads((ds / "manifest.json").read_text())
    manifest["config"] = {"viewpoints": {"height": 1.25}}  # as generate --height 1.25 records it
    (ds / "manifest.json").write_text(json.dumps(manifest))
    z = read_velodyne(ds / "training" / "velodyne" / "000000.bin")[:, 2]
    below = int((z < 0.75).sum())
    assert 0 < below < len(z)

    def view(*args) -> dict:
        code, out = run("view", ds, "--frame", "0", "--size", "320", "240", "--json", *args)
        assert code == 0, out
        return json.loads(out)

    cut = view("--out", tmp_path / "default.png")
    assert (cut["zmax"], cut["points"], cut["above_zmax"]) == (0.75, below, len(z) - below)
    everything = view("--out", tmp_path / "none.png", "--zmax", "none")
    assert (everything["zmax"], everything["points"], everything["above_zmax"]) == (None, len(z), 0)
    view("--out", tmp_path / "explicit.png", "--zmax", "0.75")
    # what is drawn: the default picture is the explicit cut's, and the ceiling's points change it
    assert (tmp_path / "default.png").read_bytes() == (tmp_path / "explicit.png").read_bytes()
    assert not np.array_equal(rgb(tmp_path / "default.png"), rgb(tmp_path / "none.png"))
    code, text = run("view", ds, "--frame", "0", "--out", tmp_path / "t.png", "--size", "320", "240")
    assert code == 0 and f"{below} points ({len(z) - below} at z >= 0.75 m left out; --zmax none draws them)" in text
    code, out = run("view", KITTI, "--frame", "0", "--out", tmp_path / "k.png", "--size", "320", "240", "--json")
    kitti = json.loads(out)
    assert code == 0 and kitti["zmax"] is None and kitti["above_zmax"] == 0
    assert kitti["points"] == len(read_velodyne(KITTI / "training" / "velodyne" / "000000.bin"))
    code, out = run("view", ds, "--frame", "0", "--out", tmp_path / "bad.png", "--zmax", "ceiling")
    assert code == 2 and "'ceiling' is not a number, auto or none" in out and not (tmp_path / "bad.png").exists()


def test_view_3d_on_kitti(tmp_path):
    out = tmp_path / "k.png"
    code, text = run("view", KITTI, "--frame", "1", "--out", out, "--3d", "--size", "400", "300")
    assert code == 0, text
    assert_picture(out, (400, 300))
    image = assert_picture(tmp_path / "k-3d.png", (400, 300))
    assert near(image, "#00b050", tol=60) > 20  # the green box wireframes


def _cube(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned closed box mesh with outward normals (12 triangles)."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], dtype=np.float64)
    f = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5],
                  [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]], dtype=np.int64)
    return v, f


def test_render_house_arrays(tmp_path):
    # A room: floor slab, a ceiling slab above it (its top faces up like a roof, so it is hidden by face mask) and
    # a chair block; the chair must come out orange, and hiding the ceiling must uncover it.
    parts = [_cube((0, 0, -0.1), (6, 4, 0)), _cube((0, 0, 2.6), (6, 4, 2.7)), _cube((2, 1, 0), (2.6, 1.6, 0.9))]
    verts, faces, owner = [], [], []
    for k, (v, f) in enumerate(parts):
        faces.append(f + sum(len(p[0]) for p in parts[:k]))
        verts.append(v)
        owner += [k] * len(f)
    v, f, owner = np.concatenate(verts), np.concatenate(faces), np.asarray(owner)
    box = np.array([[2.3, 1.3, 0.45, 0.6, 0.6, 0.9, 0.0]])
    vp = np.array([[1.0, 2.0, 1.0, 0.0], [5.0, 3.0, 1.0, math.pi]])
    covered, shown = tmp_path / "covered.png", tmp_path / "shown.png"
    render_house(v, f, covered, highlight_faces=owner == 2, highlight_boxes=box, viewpoints=vp, size=(500, 400))
    render_house(v, f, shown, highlight_faces=owner == 2, highlight_boxes=box, viewpoints=vp, size=(500, 400),
                 hidden_faces=owner == 1)
    a, b = assert_picture(covered, (500, 400), 10), assert_picture(shown, (500, 400), 10)
    # below the legend (the top tenth, whose orange swatch both pictures share): the chair fill uncovered (its box
    # outline always)
    a, b = a[int(0.1 * 400):], b[int(0.1 * 400):]
    assert near(b, "#ff7f0e", 30) > 3 * near(a, "#ff7f0e", 30) > 0  # (the legend leaves smaller panels)
    assert near(b, "#1f4fff", 40) > 20  # viewpoints


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """One synthetic house and a 1-frame dataset made by ``mpchair.dataset.generate``."""
    base = tmp_path_factory.mktemp("gen")
    (house_id,) = write_synthetic_houses(base / "houses", 1, seed=3)
    generate(GenerateRequest(root=base / "houses", houses=(house_id,), frames=1, out=base / "ds", progress=False))
    return base / "houses", house_id, base / "ds"


@pytest.mark.slow
def test_generated_dataset_stats_and_pictures(generated, tmp_path, capsys):
    houses, house_id, ds = generated
    code, out = run("stats", "--density", ds, "--json")
    assert code == 0, out
    data = json.loads(out)
    for f in data["frames"]:
        points = read_velodyne(ds / "training" / "velodyne" / f"{f['id']}.bin")
        assert (f["pillars"], f["density"]) == independent_density(points, MATTERPORT_GEOMETRY)
    manifest = json.loads((ds / "manifest.json").read_text())
    code, out = run("stats", "--boxes", ds, "--json")
    assert code == 0, out
    boxes = json.loads(out)
    kept = [len(fr["kept"]) for fr in manifest["frames"]]
    assert [f["boxes"] for f in boxes["per_frame"]] == kept
    expected_rej: dict[str, int] = {}
    for fr in manifest["frames"]:
        for r in fr["rejected"]:
            expected_rej[r["reason"]] = expected_rej.get(r["reason"], 0) + 1
    assert (boxes["rejected"] or {}) == expected_rej
    code, out = run("view", ds, "--frame", "0", "--out", tmp_path / "f.png", "--size", "500", "500", "--json")
    assert code == 0, out
    info = json.loads(out)  # the default cut, 2 m above the floor, leaves the synthetic house's ceiling out
    scan = read_velodyne(ds / "training" / "velodyne" / "000000.bin")
    assert info["zmax"] == 1.0 and info["above_zmax"] == int((scan[:, 2] >= 1.0).sum()) > 0
    assert_picture(tmp_path / "f.png", (500, 500))
    code, out = run("view-house", "--root", houses, "--house", house_id, "--dataset", ds, "--out",
                    tmp_path / "h.png", "--size", "900", "500", "--json")
    assert code == 0, out
    info = json.loads(out)
    assert info["viewpoints"] == 1 and info["objects"] > 0
    image = assert_picture(tmp_path / "h.png", (900, 500), 10)
    assert near(image, "#ff7f0e", 30) > 50 and near(image, "#1f4fff", 40) > 5
    code, out = run_main(capsys, "view-house", "--root", houses, "--house", "nope", "--out", tmp_path / "n.png")
    assert code == 2 and "house 'nope' not found" in out and not (tmp_path / "n.png").exists()


def test_view_draws_a_stream_frame_with_sequence(tmp_path, capsys):
    """``mpchair view STREAM --frame 5 --out x.png`` says how (``--sequence NN``, the sequences listed) instead of
    "no training/velodyne/000005.bin"; with ``--sequence`` it draws that sequence's frame: its points below the
    ceiling cut of the stream's sensor height, its labelled boxes."""
    from mpchair.kitti import read_labels
    from mpchair.stream import StreamRequest, stream
    from mpchair.synth import synthesize_house, write_house

    house = synthesize_house(7, levels=1)
    write_house(tmp_path / "houses", house)
    out = tmp_path / "stream"
    stream(StreamRequest(root=tmp_path / "houses", houses=(house.id,), episodes=2, out=out, rate=2.0, duration=4.0,
                         look_around=False, min_geodesic=3.0, seed=2, progress=False, height=0.8))
    code, output = run_main(capsys, "view", out, "--frame", "5", "--out", tmp_path / "x.png")
    assert code == 2 and "pick the sequence with --sequence NN (it has 00, 01)" in output, output
    code, output = run_main(capsys, "view", out, "--sequence", "07", "--frame", "5", "--out", tmp_path / "x.png")
    assert code == 2 and "no sequence 07 (it has 00, 01)" in output, output
    pic = tmp_path / "pics" / "x.png"
    code, output = run_main(capsys, "view", out, "--sequence", "01", "--frame", "5", "--out", pic,
                            "--json", "--size", "400", "300")
    assert code == 0, output
    info = json.loads(output)
    seq = out / "sequences" / "01"
    points = read_velodyne(seq / "velodyne" / "000005.bin")
    assert info["zmax"] == pytest.approx(2.0 - 0.8)  # the ceiling cut above the stream's own sensor height
    assert info["points"] == int((points[:, 2] < 2.0 - 0.8).sum()) > 0
    assert info["boxes"] == len(read_labels(seq / "label_2" / "000005.txt").objects())
    assert_picture(pic, (400, 300))
    # a stream of one sequence needs no --sequence: it draws that sequence's frame
    import shutil

    single = tmp_path / "single"
    shutil.copytree(out, single)
    shutil.rmtree(single / "sequences" / "00")
    code, output = run_main(capsys, "view", single, "--frame", "5", "--out", tmp_path / "s.png", "--json", "--size",
                            "400", "300")
    assert code == 0, output
    assert {k: v for k, v in json.loads(output).items() if k != "out"} == {
        k: v for k, v in info.items() if k != "out"}


def _figures(monkeypatch) -> list:
    """The matplotlib figures the render functions save, kept for inspection (nothing written)."""
    from mpchair.analysis import render

    saved: list = []
    monkeypatch.setattr(render, "_save_figure", lambda fig, out: saved.append(fig))
    return saved


def test_stats_plots_tell_their_curves_and_bands_apart(small, monkeypatch):
    """The density plot's shaded bands have legend entries (the paper's min-max), and a one-class dataset's l, w and
    h histograms (one axis) have three colours, each in the legend."""
    from matplotlib.colors import to_hex

    from mpchair.analysis import render
    from mpchair.analysis.stats import box_stats, density_stats

    saved = _figures(monkeypatch)
    render.plot_density_histogram(density_stats(small, MATTERPORT_GEOMETRY), "d.png")
    labels = [t.get_text() for t in saved[-1].axes[0].get_legend().get_texts()]
    assert any(t.startswith("paper Matterport-Chair: min-max ") for t in labels), labels
    assert any(t.startswith("paper KITTI: min-max ") for t in labels), labels
    stats = box_stats(small, classes=["Chair"])
    assert list(stats["classes"]) == ["Chair"]
    render.plot_box_stats(stats, "b.png")
    sizes = saved[-1].axes[1]
    colours = {to_hex(p.get_edgecolor()) for p in sizes.patches}
    assert len(colours) == 3, colours
    assert [t.get_text().split()[0] for t in sizes.get_legend().get_texts()] == ["l", "w", "h"]


def test_pictures_explain_themselves(small, monkeypatch):
    """Issue 50's pictures: the density plot's legend lies beside the axes (inside, it covered the KITTI median line)
    and its x label says the grid as the docs do (768 x 512); every box-statistics histogram has a y label; the house
    picture has a legend of its colours; BEV labels are 10 pt dark text on an opaque tag."""
    from matplotlib.colors import to_hex

    from mpchair.analysis import render
    from mpchair.analysis.stats import box_stats, density_stats

    saved = _figures(monkeypatch)
    render.plot_density_histogram(density_stats(small, MATTERPORT_GEOMETRY), "d.png")
    fig = saved[-1]
    ax = fig.axes[0]
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    assert ax.get_legend().get_window_extent(renderer).x0 >= ax.get_window_extent(renderer).x1
    assert ax.get_legend().get_window_extent(renderer).x1 <= fig.bbox.x1  # and inside the picture
    assert "(768 x 512 cells)" in ax.get_xlabel()
    render.plot_box_stats(box_stats(small, classes=["Chair"]), "b.png")
    histograms = saved[-1].axes[:7]
    assert all(a.get_ylabel() for a in histograms), [a.get_title() for a in histograms if not a.get_ylabel()]

    verts = np.array([[0, 0, 0], [4, 0, 0], [0, 4, 0], [4, 4, 1]], dtype=float)
    render.render_house(verts, np.array([[0, 1, 2], [1, 3, 2]]), "h.png", highlight_faces=np.array([False, True]),
                        viewpoints=np.array([[1.0, 1.0, 0.0, 0.5]]), highlight_label="chair objects")
    (legend,) = saved[-1].legends
    assert [t.get_text() for t in legend.get_texts()] == [
        "floors and tops (lighter = higher)", "walls (outlines)", "chair objects", "viewpoints (position, heading)"]

    boxes = np.array([[2.0, 1.0, -0.5, 1.0, 0.5, 0.8, 0.6]])
    render.render_bev(np.zeros((1, 4)), boxes, "f.png", names=["Chair"])
    (tag,) = [t for t in saved[-1].axes[0].texts if t.get_text() == "Chair"]
    assert tag.get_fontsize() >= 10 and to_hex(tag.get_color()) == "#111111"
    assert tag.get_bbox_patch().get_alpha() >= 0.9


def test_bev_labels_sit_on_their_own_box():
    """A label's anchor is a corner of its own box (the top-most one), not the bounding corner (max x, max y) that a
    rotated box does not reach."""
    from mpchair.analysis.render import label_anchors
    from mpchair.geometry import bev_polygons

    boxes = np.array([[2.0, 1.0, 0.0, 1.0, 0.5, 0.8, 0.6], [3.0, -1.0, 0.0, 0.6, 0.6, 0.9, -1.2]])
    anchors = label_anchors(boxes)
    polys = bev_polygons(boxes)
    for anchor, poly in zip(anchors, polys):
        assert np.any(np.all(np.isclose(poly, anchor), axis=1))  # a corner of the box
        assert anchor[1] == pytest.approx(poly[:, 1].max())
        assert not np.any(np.all(np.isclose(poly, poly.max(axis=0)), axis=1))  # the old anchor was not a corner


def test_3d_view_has_axes_and_a_title(tmp_path):
    """``--3d``: an x / y / z axes marker in the lower left and the frame's title in the upper left."""
    from mpchair.analysis.render import render_frame_3d

    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(1, 6, 2000), rng.uniform(-3, 3, 2000), rng.uniform(-1, 1, 2000)]
    boxes = np.array([[3.0, 0.0, 0.0, 1.0, 0.6, 0.9, 0.3]])
    render_frame_3d(points, boxes, tmp_path / "plain.png", size=(400, 300))
    render_frame_3d(points, boxes, tmp_path / "titled.png", size=(400, 300), title="dataset frame 000001")
    image = rgb(tmp_path / "titled.png")
    assert near(image[:30, :200], "#ffffff", tol=60) > 30  # the title's white text
    assert near(rgb(tmp_path / "plain.png")[:30, :200], "#ffffff", tol=60) < near(image[:30, :200], "#ffffff", 60)
    corner = image[-60:, :80]
    assert near(corner, "#0000ff", tol=90) + near(corner, "#ff0000", tol=90) > 5  # the axes marker's arrows
