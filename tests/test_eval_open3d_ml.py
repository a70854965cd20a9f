"""``--protocol open3d-ml``: the reference's own metric (Open3D-ML's ``mAP``) on our labels, against a direct call of
Open3D-ML on the same boxes built the way the reference built them (sensor-frame ``BEVBox3D`` objects)."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from detector.cli import main
from detector.eval import evaluate, evaluate_folders, evaluate_open3d_ml, format_table
from detector.eval.open3d_ml import REFERENCE_SIMILAR_CLASSES
from detector.infer import evaluate_checkpoint
from mpchair.core.errors import InputError
from mpchair.geometry import boxes_to_kitti_camera, labels_to_boxes, make_tr_velo_to_cam
from mpchair.kitti import Calib, Labels, write_imageset, write_labels

pytest.importorskip("open3d._ml3d.metrics", reason="Open3D-ML (the project's open3d extra) is not installed")

#: (l, w, h) metres per class; Van is evaluated too, so Open3D-ML's similar_classes lookup (Van -> Car) acts.
SIZES = {"Chair": (0.6, 0.55, 0.9), "Car": (3.9, 1.6, 1.5), "Pedestrian": (0.8, 0.6, 1.7), "Van": (5.0, 1.9, 2.2)}
CLASSES = ["Chair", "Car", "Pedestrian", "Van"]


def _calib() -> Calib:
    P = np.array([[500.0, 0.0, 600.0, 0.0], [0.0, 500.0, 180.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    eye34 = np.hstack([np.eye(3), np.zeros((3, 1))])
    return Calib(P0=P, P1=P, P2=P, P3=P, R0_rect=np.eye(3), Tr_velo_to_cam=make_tr_velo_to_cam((0.1, -0.3, 0.2)),
                 Tr_imu_to_velo=eye34)


def _labels(boxes: np.ndarray, names: list[str], calib: Calib, scores: np.ndarray | None = None) -> Labels:
    """KITTI labels (rectified camera frame) of sensor-frame boxes, with a plain 60 px tall 2D box each."""
    loc, hwl, ry, alpha = boxes_to_kitti_camera(boxes, calib)
    n = len(names)
    bbox = np.tile([100.0, 100.0, 160.0, 160.0], (n, 1))
    return Labels(names=names, truncated=np.zeros(n), occluded=np.zeros(n), alpha=alpha, bbox=bbox, dims_hwl=hwl,
                  location=loc, rotation_y=ry, score=scores)


def _frames(seed: int, n_frames: int = 16):
    """Sensor-frame scenes of mixed classes (and DontCare): GT, and detections that are noisy copies of ~75 % of the
    objects (some of another class, some Vans on Cars), duplicates and clutter, with tied scores here and there."""
    rng = np.random.default_rng(seed)
    calib = _calib()
    gt, dt = [], []
    for _ in range(n_frames):
        n = int(rng.integers(0, 9))
        names = [str(rng.choice(CLASSES, p=[0.35, 0.3, 0.2, 0.15])) for _ in range(n)]
        boxes = np.array([[rng.uniform(3, 40), rng.uniform(-15, 15), 0.0, *SIZES[c], rng.uniform(-np.pi, np.pi)]
                          for c in names]).reshape(-1, 7)
        boxes[:, 0] += 12.0 * np.arange(n)  # apart from each other: the frame's geometry, not overlaps, decides
        boxes[:, 2] = boxes[:, 5] / 2 + rng.normal(0, 0.05, n)
        g = _labels(boxes, names, calib)
        dontcare = Labels(names=["DontCare"], truncated=[-1], occluded=[-1], alpha=[-10], bbox=[[0, 0, 50, 50]],
                          dims_hwl=[[-1, -1, -1]], location=[[-1000, -1000, -1000]], rotation_y=[-10])
        gt.append(Labels(**{f: np.concatenate([getattr(g, f), getattr(dontcare, f)]) for f in
                            ("names", "truncated", "occluded", "alpha", "bbox", "dims_hwl", "location", "rotation_y")}))
        det_boxes, det_names = [], []
        for box, name in zip(boxes, names):
            for _ in range(int(rng.choice([0, 1, 1, 1, 2]))):  # missed, found, or found twice
                noisy = box + np.r_[rng.normal(0, 0.06 * box[3], 2), rng.normal(0, 0.1), rng.normal(0, 0.08, 3),
                                    rng.normal(0, 0.15)]
                det_boxes.append(noisy)
                det_names.append(name if rng.uniform() < 0.9 else str(rng.choice(CLASSES)))
            if name == "Car" and rng.uniform() < 0.3:  # a Van detection on a Car: its similar class, not an FP
                det_boxes.append(box + np.r_[rng.normal(0, 0.05, 2), 0, 0, 0, 0, 0])
                det_names.append("Van")
        for _ in range(int(rng.integers(0, 3))):  # clutter
            c = str(rng.choice(CLASSES))
            det_boxes.append([rng.uniform(3, 60), rng.uniform(-20, 20), SIZES[c][2] / 2, *SIZES[c],
                              rng.uniform(-np.pi, np.pi)])
            det_names.append(c)
        scores = np.round(rng.uniform(0.1, 1.0, len(det_names)), 2)
        dt.append(_labels(np.array(det_boxes).reshape(-1, 7), det_names, calib, scores))
    return gt, dt, calib


def _reference_call(gt: list[Labels], dt: list[Labels], calib: Calib, bev: bool) -> np.ndarray:
    """What the reference's pipeline did: sensor-frame ``BEVBox3D`` boxes (geometric centre, size ``[l, h, w]``,
    no calibration, hence difficulty 0) -> ``BEVBox3D.to_dicts`` -> ``mAP``."""
    from open3d._ml3d.datasets.utils import BEVBox3D
    from open3d._ml3d.metrics import mAP

    def dicts(labels: Labels) -> dict:
        labels = labels.objects()
        boxes = labels_to_boxes(labels, calib)
        scores = labels.score if labels.score is not None else np.ones(len(labels))
        return BEVBox3D.to_dicts([BEVBox3D(b[:3], b[[3, 5, 4]], b[6], name.lower(), s)
                                  for b, name, s in zip(boxes, labels.names, scores)])

    overlaps = [0.5, 0.7, 0.5, 0.7]
    return mAP([dicts(d) for d in dt], [dicts(g) for g in gt], [c.lower() for c in CLASSES], [0], overlaps, bev=bev,
               similar_classes=dict(REFERENCE_SIMILAR_CLASSES))


def test_equals_a_direct_call_of_open3d_ml_on_the_reference_boxes():
    gt, dt, calib = _frames(3)
    result = evaluate_open3d_ml(gt, dt, CLASSES)
    for metric, bev in (("bev", True), ("3d", False)):
        expected = _reference_call(gt, dt, calib, bev)
        for i, cls in enumerate(CLASSES):
            assert result.ap[cls][metric] == float(expected[i, 0, 0]), (cls, metric)
    for cls in CLASSES:
        assert result.num_gt[cls] == sum(int(np.count_nonzero(g.names == cls)) for g in gt)
        assert 0 < result.ap[cls]["bev"] < 100 and 0 < result.ap[cls]["3d"] < 100, cls  # FPs and misses count
    assert result.min_overlaps["Chair"] == (0.5, 0.5) and result.min_overlaps["Car"] == (0.7, 0.7)
    assert result.to_json_dict()["Chair"] == {"bev": result.ap["Chair"]["bev"], "3d": result.ap["Chair"]["3d"]}


def test_open3d_ml_averages_precision_over_the_recall_it_reaches():
    """Its rule, not KITTI's: with fewer than 41 sampled thresholds AP is the mean precision over them, so finding
    half of the chairs perfectly scores 100 (KITTI overall: R40 10, R11 2/11)."""
    calib = _calib()
    boxes = np.array([[4.0 + 3 * i, 0.0, 0.45, 0.6, 0.55, 0.9, 0.3 * i] for i in range(10)])
    gt = [_labels(boxes, ["Chair"] * 10, calib)]
    dt = [_labels(boxes[:5], ["Chair"] * 5, calib, np.linspace(0.9, 0.5, 5))]
    result = evaluate_open3d_ml(gt, dt, ["chair"])
    assert result.ap["chair"] == {"bev": 100.0, "3d": 100.0} and result.num_gt["chair"] == 10
    kitti = evaluate(gt, dt, ["chair"])
    assert kitti.overall["chair"]["3d"]["R40"] == pytest.approx(10.0)
    assert kitti.overall["chair"]["3d"]["R11"] == pytest.approx(200 / 11)


def _write(tmp_path, gt, dt):
    ids = [f"{i:06d}" for i in range(len(gt))]
    for fid, g, d in zip(ids, gt, dt):
        write_labels(tmp_path / "label_2" / f"{fid}.txt", g)
        write_labels(tmp_path / "results" / f"{fid}.txt", d)
    write_imageset(tmp_path / "val.txt", ids)
    return ids


def test_cli_protocol_open3d_ml(tmp_path, capsys):
    gt, dt, _ = _frames(5, n_frames=6)
    ids = _write(tmp_path, gt, dt)
    expected = evaluate_folders(tmp_path / "label_2", tmp_path / "results", ids, ["Chair", "Car"],
                                protocol="open3d-ml")
    args = ["eval", "--labels", str(tmp_path / "label_2"), "--results", str(tmp_path / "results"), "--split",
            str(tmp_path / "val.txt"), "--classes", "Chair,Car", "--protocol", "open3d-ml"]
    with pytest.raises(SystemExit) as e:
        main([*args, "--json"])
    assert e.value.code == 0
    out = json.loads(capsys.readouterr().out)
    assert out == {"protocol": "open3d-ml", "Chair": expected.ap["Chair"], "Car": expected.ap["Car"],
                   "num_gt": expected.num_gt}
    assert out["num_gt"]["Chair"] > 0 and 0 < out["Chair"]["bev"] <= 100
    with pytest.raises(SystemExit) as e:
        main(args)
    assert e.value.code == 0
    table = capsys.readouterr().out
    row = next(line for line in table.splitlines() if line.startswith("Chair"))
    assert row.split()[-3:] == [str(expected.num_gt["Chair"]), f"{expected.ap['Chair']['bev']:.2f}",
                                f"{expected.ap['Chair']['3d']:.2f}"]
    assert format_table(expected) == table.rstrip("\n")


def test_missing_open3d_ml_is_one_clear_error(tmp_path, capsys, monkeypatch):
    gt, dt, _ = _frames(1, n_frames=2)
    _write(tmp_path, gt, dt)
    monkeypatch.setitem(sys.modules, "open3d._ml3d.metrics", None)  # what a venv without Open3D-ML sees
    with pytest.raises(SystemExit) as e:
        main(["eval", "--labels", str(tmp_path / "label_2"), "--results", str(tmp_path / "results"), "--protocol",
              "open3d-ml", "--json"])
    assert e.value.code == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "pip install 'open3d-cpu[ml]'" in lines[0]
    # checkpoint mode refuses before it loads anything (no config / checkpoint needed to see the error)
    with pytest.raises(InputError, match="open3d-ml protocol needs Open3D-ML"):
        evaluate_checkpoint(tmp_path / "none.yaml", tmp_path, tmp_path / "none.pt", protocol="open3d-ml")
    with pytest.raises(InputError, match="unknown protocol"):
        evaluate_checkpoint(tmp_path / "none.yaml", tmp_path, tmp_path / "none.pt", protocol="voc")
