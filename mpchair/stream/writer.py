"""The files of a stream: KITTI-odometry-style sequence folders, written atomically (``mpchair.core.atomic``).

Layout under the output folder ``DIR``::

    sequences/NN/velodyne/NNNNNN.bin        scan, float32 x y z 1 (sensor frame), as ``generate`` writes it
    sequences/NN/label_2/NNNNNN.txt         kept chairs (KITTI, 15 columns), then DontCare rows (2D boxes) for the
                                            chairs rejected inside the labelled region
    sequences/NN/label_dontcare/NNNNNN.txt  those rejected chairs with their full 3D boxes (KITTI, 15 columns; empty
                                            file when none): KITTI's DontCare rows carry no 3D box
    sequences/NN/calib/NNNNNN.txt           the virtual camera's calibration (the same for every frame)
    sequences/NN/times.txt                  capture time of each frame, seconds with 6 decimals (integer microseconds)
    sequences/NN/poses.txt                  3x4 sensor -> world (Matterport, z up, metres) per frame, row-major
    .frames/NN/NNNNNN.json                  per-frame record; a frame is done iff its record exists (written last)
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mpchair.core.atomic import write_text
from mpchair.dataset.frame import box_labels, calib_text, dontcare_candidates, frame_labels, kitti_name
from mpchair.kitti import write_labels, write_poses, write_times, write_velodyne
from mpchair.labels.select import BoxDecisions
from mpchair.matterport.house import House
from mpchair.scan.sensors import SensorConfig, camera_calib

#: Per-frame folders of a sequence.
FRAME_DIRS = ("velodyne", "label_2", "label_dontcare", "calib")


def sequence_dir(out: Path, seq: str) -> Path:
    """``DIR/sequences/<seq>``."""
    return Path(out) / "sequences" / seq


def record_path(out: Path, seq: str, fid: str) -> Path:
    """``DIR/.frames/<seq>/<fid>.json``: the record that marks frame ``fid`` of ``seq`` as written."""
    return Path(out) / ".frames" / seq / f"{fid}.json"


def write_sequence_files(out: Path, seq: str, times_us: np.ndarray, poses: np.ndarray) -> None:
    """Write ``times.txt`` and ``poses.txt`` of one sequence."""
    d = sequence_dir(out, seq)
    write_times(d / "times.txt", times_us)
    write_poses(d / "poses.txt", poses)


def write_stream_frame(out: Path, seq: str, fid: str, house: House, decisions: BoxDecisions, points: np.ndarray,
                       sensor: SensorConfig, time_us: int, rays: int) -> dict:
    """Write frame ``fid`` of sequence ``seq`` (velodyne, label_2, label_dontcare, calib), then its record (last).

    ``decisions`` after every filter (scan points included), ``points`` (M,4) float32 sensor frame. Returns the
    record: ``{"sequence", "frame", "time_us", "points", "rays", "kept", "dontcare", "rejected": {reason: count}}``.
    """
    camera = sensor.camera
    calib = camera_calib(camera)
    size = (camera.width, camera.height)
    names = [kitti_name(house.objects[int(o)].mpcat40_name) for o in decisions.objects]
    d = sequence_dir(out, seq)
    write_velodyne(d / "velodyne" / f"{fid}.bin", points)
    write_labels(d / "label_2" / f"{fid}.txt", frame_labels(decisions, names, calib, size, dontcare=True))
    ignored = dontcare_candidates(decisions)
    write_labels(d / "label_dontcare" / f"{fid}.txt", box_labels(decisions, ignored, names, calib, size))
    write_text(d / "calib" / f"{fid}.txt", calib_text(camera))
    rejected: dict[str, int] = {}
    for r in decisions.reasons:
        if r:
            rejected[r] = rejected.get(r, 0) + 1
    record = {"sequence": seq, "frame": fid, "time_us": int(time_us), "points": len(points), "rays": int(rays),
              "kept": int(decisions.kept.sum()), "dontcare": len(ignored), "rejected": rejected}
    write_text(record_path(out, seq, fid), json.dumps(record, sort_keys=True) + "\n")
    return record
