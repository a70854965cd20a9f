"""A tiny KITTI-format dataset for detector tests, written with the ``mpchair.kitti`` writers.

Rooms are a noisy floor plus three walls around the sensor; "chairs" are dense box-shaped point clusters (labelled
``Chair``) and each frame also has one larger "table" cluster (labelled ``Table``, another class) and one DontCare row.
The calibration is mpchair's: ``R0_rect`` = identity, ``Tr_velo_to_cam`` the sensor → camera axis swap, a pinhole
``P2`` whose image holds every chair (so projected 2D boxes are large and untruncated: every chair is "Easy").
The scenes fit the smoke configs (``detector/configs/mpchair_*_smoke.yaml``: x 0-6.4 m, |y| < 4.8 m, box bottoms at
z = 0 in the sensor frame).
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
from PIL import Image

from detector.data import bev_boxes_overlap
from mpchair.core.atomic import write_bytes
from mpchair.geometry import boxes_to_kitti_camera, make_tr_velo_to_cam, project_boxes_to_image
from mpchair.kitti import (
    Calib,
    Labels,
    frame_paths,
    imageset_path,
    write_calib,
    write_imageset,
    write_labels,
    write_velodyne,
)

IMAGE_SIZE = (1242, 375)  # (W, H) pixels
FOCAL = 400.0  # px: a 0.9 m chair at 6 m is 60 px tall (KITTI "Easy" needs > 40 px)
FLOOR_Z = 0.0  # sensor frame, metres (the sensor sits on the floor, so box bottoms are at z = 0 like the anchors)
CHAIR_SIZE = (0.60, 0.55, 0.90)  # mean l, w, h (m)
ROOM = (0.3, 6.2, -4.6, 4.6)  # x_min, x_max, y_min, y_max of the floor (m): inside the smoke configs' range


def tiny_calib() -> Calib:
    """mpchair-style calibration with a ``FOCAL`` px pinhole at the image centre."""
    W, H = IMAGE_SIZE
    P = np.array([[FOCAL, 0.0, W / 2, 0.0], [0.0, FOCAL, H / 2, 0.0], [0.0, 0.0, 1.0, 0.0]])
    imu = np.hstack([np.eye(3), np.zeros((3, 1))])
    return Calib(P0=P, P1=P, P2=P, P3=P, R0_rect=np.eye(3), Tr_velo_to_cam=make_tr_velo_to_cam(), Tr_imu_to_velo=imu)


def _box_points(box: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n,3) points on the surface of a (7,) box, 2 cm inside its faces (labels are rounded to 1 cm), sensor frame."""
    l, w, h = box[3:6] - 0.04
    local = rng.uniform(-0.5, 0.5, size=(n, 3)) * np.array([l, w, h])
    axis = rng.integers(0, 3, size=n)  # push each point onto a face of a random axis (a hollow, scan-like shell)
    local[np.arange(n), axis] = np.sign(local[np.arange(n), axis]) * np.array([l, w, h])[axis] * 0.5
    c, s = np.cos(box[6]), np.sin(box[6])
    out = np.empty_like(local)
    out[:, 0] = c * local[:, 0] - s * local[:, 1] + box[0]
    out[:, 1] = s * local[:, 0] + c * local[:, 1] + box[1]
    out[:, 2] = local[:, 2] + box[2]
    return out


def _place(rng: np.random.Generator, size: np.ndarray, taken: list[np.ndarray], x_range=(2.2, 5.6)) -> np.ndarray:
    """A box of ``size`` (l, w, h) on the floor, inside the camera view, not overlapping ``taken`` in BEV."""
    for _ in range(100):
        x = rng.uniform(*x_range)
        half_fov = 0.75 * (IMAGE_SIZE[0] / 2) / FOCAL  # tan of 75% of the half FOV: keeps boxes off the border
        y_max = min(half_fov * x - 0.5, ROOM[3] - 0.8)
        y = rng.uniform(-y_max, y_max)
        box = np.array([x, y, FLOOR_Z + size[2] / 2, *size, rng.uniform(-np.pi, np.pi)])
        grown = box.copy()
        grown[3:5] += 0.3  # keep a gap so clusters stay separable
        if not taken or not bev_boxes_overlap(grown[None], np.stack(taken)).any():
            return box
    raise RuntimeError("could not place a box")


def make_frame(rng: np.random.Generator, n_chairs: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One synthetic scene: (N,4) float32 points, (M,7) sensor boxes and (M,) names (chairs then one table)."""
    parts = []
    x0, x1, y0, y1 = ROOM
    floor = np.column_stack([rng.uniform(x0, x1, 1500), rng.uniform(y0, y1, 1500), FLOOR_Z + rng.normal(0, 0.01, 1500)])
    back = np.column_stack([np.full(400, x1), rng.uniform(y0, y1, 400), rng.uniform(FLOOR_Z, 2.0, 400)])
    left = np.column_stack([rng.uniform(x0, x1, 300), np.full(300, y1), rng.uniform(FLOOR_Z, 2.0, 300)])
    right = np.column_stack([rng.uniform(x0, x1, 300), np.full(300, y0), rng.uniform(FLOOR_Z, 2.0, 300)])
    parts += [floor, back, left, right]
    boxes, names = [], []
    for _ in range(n_chairs):
        size = np.array(CHAIR_SIZE) * rng.uniform(0.9, 1.1, 3)
        box = _place(rng, size, boxes)
        boxes.append(box)
        names.append("Chair")
        parts.append(_box_points(box, int(rng.integers(150, 250)), rng))
    table = _place(rng, np.array([1.4, 0.8, 0.75]), boxes)
    boxes.append(table)
    names.append("Table")
    parts.append(_box_points(table, 300, rng))
    xyz = np.concatenate(parts)
    points = np.column_stack([xyz, rng.uniform(0, 1, len(xyz))]).astype(np.float32)
    return points, np.stack(boxes), np.array(names)


def write_frame(root: Path, frame_id: str, points: np.ndarray, boxes: np.ndarray, names: np.ndarray) -> None:
    """Write one frame's velodyne, calib, image_2 and label_2 (objects, then one DontCare row)."""
    calib = tiny_calib()
    paths = frame_paths(root, frame_id)
    write_velodyne(paths.velodyne, points)
    write_calib(paths.calib, calib)
    buf = io.BytesIO()
    Image.new("L", IMAGE_SIZE).save(buf, format="PNG")
    write_bytes(paths.image_2, buf.getvalue())
    location, dims_hwl, rotation_y, alpha = boxes_to_kitti_camera(boxes, calib)
    bbox, truncation = project_boxes_to_image(boxes, calib, IMAGE_SIZE)
    n = len(boxes)
    objects = Labels(names, truncation, np.zeros(n, dtype=np.int64), alpha, bbox, dims_hwl, location, rotation_y)
    dontcare = Labels(["DontCare"], [-1], [-1], [-10], [[10.0, 10.0, 40.0, 30.0]], [[-1, -1, -1]],
                      [[-1000, -1000, -1000]], [-10])
    write_labels(paths.label_2, Labels.concatenate([objects, dontcare]))


def make_tiny_dataset(
    root: str | Path, n_frames: int = 8, seed: int = 0, chairs: tuple[int, int] = (2, 4),
    splits: dict[str, list[int]] | None = None,
) -> Path:
    """Write ``n_frames`` frames (ids 000000..) under ``root`` plus ``ImageSets`` (default: every split = all)."""
    root = Path(root)
    rng = np.random.default_rng(seed)
    ids = [f"{i:06d}" for i in range(n_frames)]
    for fid in ids:
        points, boxes, names = make_frame(rng, int(rng.integers(chairs[0], chairs[1] + 1)))
        write_frame(root, fid, points, boxes, names)
    splits = splits or {"train": list(range(n_frames)), "val": list(range(n_frames)), "test": list(range(n_frames))}
    for name, idx in splits.items():
        write_imageset(imageset_path(root, name), [ids[i] for i in idx])
    return root


SMOKE_CONFIG = Path(__file__).resolve().parents[1] / "detector" / "configs" / "mpchair_dense_smoke.yaml"


def write_test_config(path: str | Path, *, model: dict | None = None, data: dict | None = None,
                      train: dict | None = None) -> Path:
    """A small, fast experiment for tests: the dense smoke config's geometry with a slim network (pillar features 32,
    one conv per block, 32/32/64 channels), with the given per-section overrides."""
    import yaml

    cfg = yaml.safe_load(SMOKE_CONFIG.read_text())
    cfg["model"].update(pfn_channels=32, layer_channels=[32, 32, 64], layer_nums=[1, 1, 1],
                        neck_channels=[32, 32, 32], max_points_per_pillar=16, max_pillars_train=4000,
                        max_pillars_test=4000)
    cfg["train"].update(eval_every=0, checkpoint_every=1)
    for section, values in (("model", model), ("data", data), ("train", train)):
        if values:
            for k, v in values.items():
                if isinstance(v, dict) and isinstance(cfg[section].get(k), dict):
                    cfg[section][k].update(v)
                else:
                    cfg[section][k] = v
    path = Path(path)
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


RUN_BASE_CONFIG = "mpchair_dense_cpu"  # a packaged config (it derives from another: read through experiment_yaml)


def write_run_config(run: str | Path, *, model: dict | None = None, train: dict | None = None) -> Path:
    """``RUN/config.yaml`` of a run folder as ``detector train`` writes it (every key; the CPU dense config, 288 x 144,
    with the given per-section overrides), checked by reading it back (:func:`detector.config.load_run_config`)."""
    import yaml

    from detector.config import config_file, experiment_yaml, load_run_config

    cfg = experiment_yaml(config_file(RUN_BASE_CONFIG))
    for section, values in (("model", model), ("train", train)):
        cfg[section].update(values or {})
    path = Path(run) / "config.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    load_run_config(path)
    return path


def write_manifest(dataset: str | Path, houses: dict[str, tuple[int, int, dict[str, str]]], *, height: float = 1.0,
                   robot_radius: float = 0.25) -> Path:
    """``dataset/manifest.json`` as ``mpchair generate`` writes it, less its frame records (as a run record keeps it):
    ``houses`` id -> (first frame, last frame, files_sha256), the viewpoint settings ``height`` / ``robot_radius``
    (metres); the other fields are placeholders."""
    from mpchair.dataset.manifest import MANIFEST_FORMAT, Manifest, ManifestHouse, ManifestTotals

    manifest = Manifest(
        format=MANIFEST_FORMAT, command=("mpchair", "generate", "--height", repr(height), "--robot-radius",
                                         repr(robot_radius)),
        config={"viewpoints": {"height": height, "robot_radius": robot_radius}}, versions={}, seed=0,
        houses={h: ManifestHouse(files_sha256=files, objects_of_class=1, frames=(a, b))
                for h, (a, b, files) in houses.items()},
        conventions={}, splits={}, totals=ManifestTotals(frames=0, boxes_kept=0, boxes_rejected={}, points=0),
        frames=())
    path = Path(dataset) / "manifest.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(manifest.to_json() + "\n")
    return path


def stream_summary(sap: float, offline: float | None = None, latency: float = 100.0, processed: float = 0.5, *,
                   p95_over_median: float = 1.25, staleness_ms: tuple[float, float] = (150.0, 200.0),
                   staleness_frames: tuple[float, float] = (1.5, 2.0), logical_cpus: int = 4) -> dict:
    """A ``detector stream-eval --json`` summary as the streaming study's measuring run writes it: sAP (and the
    offline AP, if any) ``sap`` percent in 3D (BEV one point higher), the median ``latency`` ms (its p95
    ``p95_over_median`` times that), staleness (mean, p95) in ms and frames, the share of frames ``processed``, 3
    repeats, a test machine of ``logical_cpus`` CPUs."""
    ap = lambda x: {"Chair": {"3d": {"R40": x, "R11": x}, "bev": {"R40": x + 1, "R11": x + 1}}}  # noqa: E731
    return {"sAP": ap(sap), "offline_AP": None if offline is None else ap(offline),
            "latency_ms": {"median": latency, "p95": latency * p95_over_median},
            "staleness_ms": dict(zip(("mean", "p95"), staleness_ms)),
            "staleness_frames": dict(zip(("mean", "p95"), staleness_frames)), "frames_processed": processed,
            "repeats": 3, "machine": {"cpu": "Test CPU", "torch_threads": 2, "torch": "2.x", "allocator": "reuse",
                                      "logical_cpus": logical_cpus}}


def onecycle_curve(total: int, peak: float, *, pct: float = 0.4, div: float = 10.0, final: float = 1e4,
                    beta1: tuple[float, float] = (0.95, 0.85)) -> list[tuple[float, float]]:
    """(lr, beta1) of steps 0..total-1 of OpenPCDet's adam_onecycle in closed form, with OneCycleLR's phase ends
    (warm-up ends at step pct * total - 1, annealing at total - 1; cosine interpolation in both phases)."""

    def cos(a: float, b: float, t: float) -> float:
        return b + (a - b) / 2 * (math.cos(math.pi * t) + 1)

    e1, e2 = pct * total - 1, total - 1
    out = []
    for i in range(total):
        if i <= e1:
            t = i / e1
            out.append((cos(peak / div, peak, t), cos(beta1[0], beta1[1], t)))
        else:
            t = (i - e1) / (e2 - e1)
            out.append((cos(peak, peak / (div * final), t), cos(beta1[1], beta1[0], t)))
    return out


def detector_cli(args: list, capsys) -> tuple[int, str, str]:
    """Run ``detector ARGS`` in this process: ``(exit status, stdout, stderr)`` (arguments turned into strings)."""
    import pytest

    from detector.cli import main

    with pytest.raises(SystemExit) as e:
        main([str(a) for a in args])
    out, err = capsys.readouterr()
    return e.value.code, out, err
