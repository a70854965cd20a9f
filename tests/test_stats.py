"""``mpchair stats``: density and box statistics checked against independent plain-Python computations, on a small
KITTI-format dataset written here with the ``mpchair.kitti`` writers and on the vendored real KITTI frames."""

from __future__ import annotations

import io
import json
import math
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from mpchair.analysis.stats import (
    KITTI_GEOMETRY,
    MATTERPORT_GEOMETRY,
    PseudoimageGeometry,
    density_stats,
    geometry_from_model_yaml,
)
from mpchair.cli import cli
from mpchair.core.atomic import write_bytes, write_text
from mpchair.dataset.manifest import (
    MANIFEST_FORMAT,
    FrameRecord,
    Manifest,
    ManifestHouse,
    ManifestTotals,
    RejectedBox,
)
from mpchair.geometry import boxes_to_kitti_camera, make_tr_velo_to_cam, project_boxes_to_image
from mpchair.kitti import (
    Calib,
    Labels,
    read_labels,
    read_velodyne,
    write_calib,
    write_imageset,
    write_labels,
    write_velodyne,
)

REPO = Path(__file__).resolve().parents[1]
KITTI = REPO / "tests" / "data" / "kitti"
IMAGE_SIZE = (640, 480)

# Boxes of the small dataset (sensor frame): frame id → [(name, [x, y, z, l, w, h, yaw], occluded, truncated)].
SMALL_BOXES = {
    "000000": [("Chair", [3.0, 1.0, -0.6, 0.9, 0.6, 0.9, 0.3], 0, 0.0),
               ("Chair", [5.0, -2.0, -0.5, 1.1, 0.7, 1.0, -1.2], 1, 0.2)],
    "000001": [("Chair", [2.0, -0.5, -0.7, 0.8, 0.5, 0.8, 2.0], 2, 0.0),
               ("Table", [4.0, 0.5, -0.8, 1.6, 0.9, 0.7, 0.0], 0, 0.0),
               ("Chair", [6.5, 2.5, -0.6, 1.0, 0.65, 0.92, -2.9], 0, 0.45)],
    "000002": [],
}


def small_calib() -> Calib:
    """A rectified pinhole camera at the sensor (R0 = I, Tr = the sensor → camera axis swap), 640 x 480 image."""
    P = np.array([[300.0, 0.0, 320.0, 0.0], [0.0, 300.0, 240.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    return Calib(P0=P, P1=P, P2=P, P3=P, R0_rect=np.eye(3), Tr_velo_to_cam=make_tr_velo_to_cam(),
                 Tr_imu_to_velo=np.eye(4)[:3])


def small_points(rng: np.random.Generator, boxes: np.ndarray) -> np.ndarray:
    """(N,4) float32: uniform clutter over and beyond the Matterport range, points inside each box, and points on the
    range's faces (min faces kept, max faces dropped by the half-open rule)."""
    clutter = np.column_stack([rng.uniform(-1, 26, 1500), rng.uniform(-20, 20, 1500), rng.uniform(-2.5, 2.5, 1500)])
    parts = [clutter]
    for b in boxes:
        local = rng.uniform(-0.45, 0.45, (60, 3)) * b[3:6]
        c, s = math.cos(b[6]), math.sin(b[6])
        parts.append(np.column_stack([b[0] + c * local[:, 0] - s * local[:, 1], b[1] + s * local[:, 0]
                                      + c * local[:, 1], b[2] + local[:, 2]]))
    parts.append(np.array([[0.0, -19.0, -2.0], [25.0, 0.0, 0.0], [1.0, 19.0, 0.0], [1.0, 0.0, 2.0],
                           [24.97, 18.97, 1.99], [0.0, 0.0, -2.0], [-0.001, 1.0, 0.0]]))
    xyz = np.concatenate(parts)
    return np.column_stack([xyz, np.ones(len(xyz))]).astype(np.float32)


def build_small_dataset(root: Path, seed: int = 7, manifest: bool = True) -> Path:
    """A 3-frame KITTI-layout dataset (velodyne, label_2 with a DontCare row, calib, image_2, ImageSets, manifest)."""
    rng = np.random.default_rng(seed)
    calib = small_calib()
    png = io.BytesIO()
    Image.new("L", IMAGE_SIZE, 0).save(png, format="PNG")
    for fid, items in SMALL_BOXES.items():
        boxes = np.array([b for _, b, _, _ in items], dtype=np.float64).reshape(-1, 7)
        write_velodyne(root / "training" / "velodyne" / f"{fid}.bin", small_points(rng, boxes))
        write_calib(root / "training" / "calib" / f"{fid}.txt", calib)
        write_bytes(root / "training" / "image_2" / f"{fid}.png", png.getvalue())
        loc, dims, ry, alpha = boxes_to_kitti_camera(boxes, calib)
        bbox, _ = project_boxes_to_image(boxes, calib, IMAGE_SIZE)
        labels = Labels([n for n, _, _, _ in items], [t for *_, t in items], [o for _, _, o, _ in items], alpha,
                        bbox, dims, loc, ry)
        dontcare = Labels(["DontCare"], [-1], [-1], [-10], [[10, 10, 50, 50]], [[-1, -1, -1]],
                          [[-1000, -1000, -1000]], [-10])
        write_labels(root / "training" / "label_2" / f"{fid}.txt", Labels.concatenate([labels, dontcare]))
    write_imageset(root / "ImageSets" / "val.txt", ["000000", "000002"])
    if manifest:
        write_text(root / "manifest.json", small_manifest().to_json() + "\n")
    return root


#: The small dataset's rejected boxes by frame (what its manifest records).
SMALL_REJECTED = {"000000": ("height", "fov"), "000001": ("height",), "000002": ()}


def small_manifest() -> Manifest:
    """The small dataset's manifest, as ``mpchair generate`` would write it for one house ``h1`` at sensor height 1 m
    (the stats read the kept boxes from label_2; only the rejected ones come from here)."""
    frames = tuple(
        FrameRecord(frame=fid, house="h1", index=i, attempt=0, views_tried=1,
                    pose=((1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 1.0, 1.0)), yaw=0.0,
                    points=1500, rays=1500, kept=(),
                    rejected=tuple(RejectedBox(object_index=k, object_id=f"0_0_{k}", class_name="chair", reason=r)
                                   for k, r in enumerate(reasons)))
        for i, (fid, reasons) in enumerate(SMALL_REJECTED.items())
    )  # fmt: skip
    rejected = Counter(b.reason for f in frames for b in f.rejected)
    return Manifest(format=MANIFEST_FORMAT, command=("mpchair", "generate"), config={"viewpoints": {"height": 1.0}},
                    versions={}, seed=7, houses={"h1": ManifestHouse({}, 8, (0, 2))}, conventions={},
                    splits={"val": 2}, totals=ManifestTotals(3, 0, dict(sorted(rejected.items())), 4500),
                    frames=frames)  # fmt: skip


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    return build_small_dataset(tmp_path_factory.mktemp("small"))


def independent_density(points: np.ndarray, geometry: PseudoimageGeometry) -> tuple[int, float]:
    """The density rule written out point by point: keep min <= p < max, cell = floor((p - min) / voxel)."""
    x0, y0, z0, x1, y1, z1 = geometry.point_cloud_range
    vx, vy = geometry.voxel_size
    nx, ny = round((x1 - x0) / vx), round((y1 - y0) / vy)
    cells = set()
    for x, y, z in points[:, :3].astype(np.float64).tolist():
        if x0 <= x < x1 and y0 <= y < y1 and z0 <= z < z1:
            cells.add((min(math.floor((y - y0) / vy), ny - 1), min(math.floor((x - x0) / vx), nx - 1)))
    W, H = geometry.grid
    return len(cells), len(cells) / (W * H)


def run(*args: str) -> tuple[int, str]:
    result = CliRunner().invoke(cli, [str(a) for a in args])
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise result.exception
    return result.exit_code, result.output


def run_main(capsys, *args: str) -> tuple[int, str]:
    """Through the console-script entry (InputError → one ``error:`` line, exit 2); stdout + stderr."""
    from mpchair.cli import main

    with pytest.raises(SystemExit) as e:
        main([str(a) for a in args])
    captured = capsys.readouterr()
    return e.value.code, captured.out + captured.err


# --------------------------------------------------------------------------------------------------------- density


def test_density_json_equals_independent_count_on_small_dataset(small):
    code, out = run("stats", "--density", small, "--json")
    assert code == 0, out
    data = json.loads(out)
    assert data["geometry"]["grid"] == [512, 768] and data["geometry"]["real_grid"] == [500, 760]
    expected = []
    for fid in ("000000", "000001", "000002"):
        points = read_velodyne(small / "training" / "velodyne" / f"{fid}.bin")
        expected.append(independent_density(points, MATTERPORT_GEOMETRY))
    assert [f["pillars"] for f in data["frames"]] == [e[0] for e in expected]
    assert [f["density"] for f in data["frames"]] == [e[1] for e in expected]
    d = sorted(e[1] for e in expected)
    assert (data["count"], data["min"], data["median"], data["max"]) == (3, d[0], d[1], d[2])
    assert data["mean"] == pytest.approx(sum(d) / 3, rel=1e-12)
    # The half-open rule on the range faces: the min corner counts, the max faces do not.
    first = read_velodyne(small / "training" / "velodyne" / "000000.bin").astype(np.float64)
    kept = int(np.sum(np.all((first[:, :3] >= [0, -19, -2]) & (first[:, :3] < [25, 19, 2]), axis=1)))
    assert data["frames"][0]["points_in_range"] == kept


def test_density_split_and_explicit_range(small):
    code, out = run("stats", "--density", small, "--split", "val", "--range", "0", "-10", "-1", "10", "10", "1",
                    "--voxel", "0.5", "0.25", "--grid", "24", "88", "--json")
    assert code == 0, out
    data = json.loads(out)
    g = PseudoimageGeometry((0.0, -10.0, -1.0, 10.0, 10.0, 1.0), (0.5, 0.25), (24, 88))
    assert [f["id"] for f in data["frames"]] == ["000000", "000002"]
    for f in data["frames"]:
        points = read_velodyne(small / "training" / "velodyne" / f"{f['id']}.bin")
        assert (f["pillars"], f["density"]) == independent_density(points, g)
    assert data["geometry"]["real_grid"] == [20, 80]


def test_density_on_vendored_kitti_matches_independent_count_and_paper_range():
    data = density_stats(KITTI, KITTI_GEOMETRY)
    cropped = density_stats(KITTI, KITTI_GEOMETRY, fov_crop=True)
    assert len(data["frames"]) == 6
    for f, g in zip(data["frames"], cropped["frames"]):
        points = read_velodyne(KITTI / "training" / "velodyne" / f"{f['id']}.bin")
        assert (f["pillars"], f["density"]) == independent_density(points, KITTI_GEOMETRY)
        # The vendored scans are already cropped to image_2, so cropping again changes nothing.
        assert (g["points"], g["pillars"]) == (f["points"], f["pillars"])
    # These 6 training frames fall inside the paper's KITTI range (min 0.013321, max 0.03899): docs/stats.md.
    assert 0.013321 <= data["min"] and data["max"] <= 0.03899
    assert data["median"] == pytest.approx(0.022998, abs=5e-6)


def test_fov_crop_uses_calib_and_image_size(small):
    a = density_stats(small, MATTERPORT_GEOMETRY)
    b = density_stats(small, MATTERPORT_GEOMETRY, fov_crop=True)
    calib = small_calib()
    for fa, fb in zip(a["frames"], b["frames"]):
        points = read_velodyne(small / "training" / "velodyne" / f"{fa['id']}.bin").astype(np.float64)
        # Independent crop: camera frame (x right = -y, y down = -z, z forward = x), then the pinhole.
        xc, yc, zc = -points[:, 1], -points[:, 2], points[:, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = calib.P2[0, 0] * xc / zc + calib.P2[0, 2]
            v = calib.P2[1, 1] * yc / zc + calib.P2[1, 2]
        inside = (zc > 0) & (u >= 0) & (u < IMAGE_SIZE[0]) & (v >= 0) & (v < IMAGE_SIZE[1])
        assert fb["points"] == int(inside.sum()) < fa["points"]
        assert (fb["pillars"], fb["density"]) == independent_density(points[inside], MATTERPORT_GEOMETRY)


GOOD_MODEL = ("model:\n  point_cloud_range: [0, -4, -1, 8, 4, 1]\n  voxel_size: [0.5, 0.5, 2]\n"
              "  output_shape: [16, 16]\n")


def test_config_yaml_picks_model_geometry(tmp_path):
    assert geometry_from_model_yaml(REPO / "detector" / "configs" / "mpchair_dense.yaml") == MATTERPORT_GEOMETRY
    assert geometry_from_model_yaml(REPO / "detector" / "configs" / "kitti_car_sparse.yaml") == KITTI_GEOMETRY
    cfg = tmp_path / "m.yaml"
    write_text(cfg, GOOD_MODEL)
    assert geometry_from_model_yaml(cfg) == PseudoimageGeometry((0, -4, -1, 8, 4, 1), (0.5, 0.5), (16, 16))


#: Model YAMLs whose pillar grid ``stats --config`` cannot read, and the message (after the file name) it gives.
BAD_GRIDS = {  # the file's text, the line the error names ("" where the key is nowhere in it), the message
    "no model section": ("train:\n  epochs: 3\n", "", "model: expected a mapping"),
    "missing key": (GOOD_MODEL.replace("  output_shape: [16, 16]\n", ""), ":1", "model.output_shape: missing"),
    "wrong type": (GOOD_MODEL.replace("[0.5, 0.5, 2]", "fine"), ":3", "model.voxel_size: expected a list"),
    "not a whole number of voxels": (GOOD_MODEL.replace("[0.5, 0.5, 2]", "[0.3, 0.5, 2]"), ":2",
                                     "model.point_cloud_range / voxel_size / output_shape: pc_range"),
    "canvas smaller than the grid": (GOOD_MODEL.replace("[16, 16]", "[8, 16]"), ":2",
                                     "model.point_cloud_range / voxel_size / output_shape: grid 16 x 8 is smaller"),
}


@pytest.mark.parametrize("case", list(BAD_GRIDS))
def test_stats_config_reads_the_grid_keys_only(small, tmp_path, capsys, case):
    """``stats --config`` reads ``model.point_cloud_range / voxel_size / output_shape`` and nothing else (mpchair never
    reads the detector's schema): a bad grid key is one ``error:`` line naming the file, the key's line (its section's
    for a missing key) and the key, no plot."""
    text, line, message = BAD_GRIDS[case]
    cfg = tmp_path / "exp.yaml"
    write_text(cfg, text)
    plot = tmp_path / "p.png"
    code, out = run_main(capsys, "stats", "--density", small, "--config", cfg, "--plot", plot)
    assert code == 2, out
    assert len(out.splitlines()) == 1 and out.startswith(f"error: {cfg}{line}: {message}"), out
    assert not plot.exists()


def test_stats_config_help_says_only_the_grid_is_checked(capsys):
    """The help promises no more than the command does: only the pillar grid of --config is read and checked."""
    code, out = run_main(capsys, "stats", "--help")
    text = " ".join(out.split())
    assert code == 0 and "validated whole" not in text
    assert "only its pillar grid is read and checked" in text and "detector train validates the whole file" in text


def test_stats_config_ignores_the_detector_keys(tmp_path):
    """Keys only the detector knows (training, eval, unknown model keys) do not change the grid mpchair reads."""
    cfg = tmp_path / "exp.yaml"
    write_text(cfg, GOOD_MODEL + "  backbone: sparse\ntrain:\n  epochs: 3\n")
    assert geometry_from_model_yaml(cfg) == PseudoimageGeometry((0, -4, -1, 8, 4, 1), (0.5, 0.5), (16, 16))


def test_density_plot_png(small, tmp_path):
    out = tmp_path / "d.png"
    code, text = run("stats", "--density", small, "--plot", out)
    assert code == 0, text
    assert "median" in text and str(out) in text
    with Image.open(out) as im:
        rgb = np.asarray(im.convert("RGB"))
    assert rgb.shape == (500, 900, 3)
    assert rgb.std() > 20 and len(np.unique(rgb.reshape(-1, 3), axis=0)) > 20


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--density", "{missing}"], "dataset folder not found"),
        (["--density", "{small}", "--grid", "400", "400", "--range", "0", "-19", "-2", "25", "19", "2", "--voxel",
          "0.05", "0.05"], "grid 400 x 400 is smaller than the range's 500 x 760 pillars"),
        (["--density", "{small}", "--range", "0", "-19", "-2", "25", "19", "2", "--voxel", "0.07", "0.05"],
         "not a whole number of voxels"),
        (["--density", "{small}", "--split", "train"], "ImageSets/train.txt: image set file not found"),
        (["--density", "{small}", "--config", "{small}/nope.yaml"], "config file not found"),
    ],
)
def test_bad_input_is_one_line_exit_2_and_no_plot(small, tmp_path, capsys, args, needle):
    plot = tmp_path / "p.png"
    args = [a.format(small=small, missing=tmp_path / "missing") for a in args]
    code, out = run_main(capsys, "stats", *args, "--plot", plot)
    assert code == 2, out
    lines = out.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], out
    assert not plot.exists()


def test_truncated_scan_names_the_file(tmp_path, capsys):
    root = build_small_dataset(tmp_path / "ds", manifest=False)
    bad = root / "training" / "velodyne" / "000001.bin"
    bad.write_bytes(bad.read_bytes()[:-3])
    code, out = run_main(capsys, "stats", "--density", root, "--json")
    assert code == 2 and out.count("\n") == 1 and str(bad) in out and "not a multiple of 16" in out


def test_usage_errors():
    code, out = run("stats", str(KITTI))
    assert code == 2 and "choose --density or --boxes" in out
    code, out = run("stats", "--density", str(KITTI), "--preset", "kitti", "--range", "0", "0", "0", "1", "1", "1",
                    "--voxel", "1", "1")
    assert code == 2 and "exclusive" in out


# ----------------------------------------------------------------------------------------------------------- boxes


def test_box_stats_equal_independent_values(small):
    code, out = run("stats", "--boxes", small, "--json")
    assert code == 0, out
    data = json.loads(out)
    assert data["frames"] == 3
    assert [f["boxes"] for f in data["per_frame"]] == [2, 3, 0]  # DontCare rows are not boxes
    assert data["boxes_per_frame"]["histogram"] == {"0": 1, "1": 0, "2": 1, "3": 1}
    assert set(data["classes"]) == {"Chair", "Table"}
    chair = data["classes"]["Chair"]
    assert chair["count"] == 4
    # Dimensions as the label files hold them (h w l, 2 decimals), read independently of the stats code.
    rows = [line.split() for fid in ("000000", "000001")
            for line in (small / "training" / "label_2" / f"{fid}.txt").read_text().splitlines()]
    chairs = [r for r in rows if r[0] == "Chair"]
    ls = [float(r[10]) for r in chairs]
    ws = [float(r[9]) for r in chairs]
    hs = [float(r[8]) for r in chairs]
    assert chair["l"]["mean"] == pytest.approx(sum(ls) / 4, abs=1e-12)
    assert chair["w"]["std"] == pytest.approx(float(np.std(ws)), abs=1e-12)
    assert chair["anchor_lwh"] == pytest.approx([sum(ls) / 4, sum(ws) / 4, sum(hs) / 4], abs=1e-12)
    assert chair["occluded"] == {"0": 2, "1": 1, "2": 1}
    assert chair["truncated"]["max"] == pytest.approx(0.45)
    # Points per box and distance, by a plain loop over the scan in each box's own frame.
    expected_points, expected_dist, expected_yaw = [], [], []
    for fid in ("000000", "000001"):
        points = read_velodyne(small / "training" / "velodyne" / f"{fid}.bin")[:, :3].astype(np.float64).tolist()
        labels = read_labels(small / "training" / "label_2" / f"{fid}.txt").objects()
        for k in range(len(labels)):
            if labels.names[k] != "Chair":
                continue
            h, w, l = labels.dims_hwl[k]
            # sensor = (z_cam, -x_cam, -y_cam) for this calib; the centre is h/2 above the bottom centre.
            cx, cy, cz = labels.location[k][2], -labels.location[k][0], -labels.location[k][1] + h / 2
            yaw = -labels.rotation_y[k] - math.pi / 2
            c, s = math.cos(yaw), math.sin(yaw)
            n = 0
            for x, y, z in points:
                dx, dy, dz = x - cx, y - cy, z - cz
                if abs(c * dx + s * dy) <= l / 2 and abs(-s * dx + c * dy) <= w / 2 and abs(dz) <= h / 2:
                    n += 1
            expected_points.append(n)
            expected_dist.append(math.hypot(cx, cy))
            expected_yaw.append(yaw)
    got = sorted(expected_points)
    assert chair["points"]["min"] == got[0] and chair["points"]["max"] == got[-1]
    assert chair["points"]["median"] == (got[1] + got[2]) / 2 and got[0] >= 60
    assert chair["distance"]["max"] == pytest.approx(max(expected_dist), abs=1e-9)
    # Yaw histogram: 12 bins of 30 degrees over [-pi, pi), each chair in the bin of its (wrapped) label heading.
    expected_counts = [0] * 12
    for yaw in expected_yaw:
        expected_counts[int(((yaw + math.pi) % (2 * math.pi)) // (math.pi / 6))] += 1
    assert chair["yaw"]["histogram"]["counts"] == expected_counts and max(expected_counts) < 4  # spread over bins
    assert chair["yaw"]["histogram"]["edges"] == pytest.approx([-math.pi + k * math.pi / 6 for k in range(13)])
    assert data["rejected"] == {"height": 2, "fov": 1}


def test_box_stats_on_vendored_kitti_and_plot(tmp_path):
    out = tmp_path / "b.png"
    code, text = run("stats", "--boxes", KITTI, "--class", "Car", "--json", "--plot", out)
    assert code == 0, text
    data = json.loads(text)
    assert list(data["classes"]) == ["Car"] and data["classes"]["Car"]["count"] == 5
    code, lower = run("stats", "--boxes", KITTI, "--class", "car", "--json")  # case-insensitive, like detector eval
    assert code == 0 and json.loads(lower)["classes"] == data["classes"]
    assert data["rejected"] is None
    # The real sample's cars hold 9 (000001), 67 (000002), 674 (000003), 78 and 26 (000004) LiDAR points (the counts
    # tests/test_data_kitti.py pins for every labelled box).
    cars = [9, 67, 674, 78, 26]
    points = data["classes"]["Car"]["points"]
    assert (points["count"], points["min"], points["median"], points["max"]) == (5, 9, 67, 674)
    assert points["mean"] == pytest.approx(sum(cars) / 5, abs=1e-12)
    with Image.open(out) as im:
        rgb = np.asarray(im.convert("RGB"))
    assert rgb.shape == (800, 1600, 3) and rgb.std() > 20 and len(np.unique(rgb.reshape(-1, 3), axis=0)) > 30
