"""What both recorders (Rerun, ROS 2 / MCAP) read from a stream or dataset folder: the stream's metadata, one
sequence's times and poses, one frame's boxes. Sensor frame (x forward, y left, z up), metres."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mpchair.core.errors import InputError
from mpchair.core.text import load_json
from mpchair.geometry import labels_to_boxes
from mpchair.kitti import read_calib, read_labels, read_poses, read_times


def read_stream_meta(root: Path) -> tuple[dict, Path]:
    """``(stream.json as a dict, its path)`` of a stream folder; a missing, unreadable or malformed file (no
    ``sequences`` mapping) is an :class:`InputError` naming it."""
    path = root / "stream.json"
    if not path.is_file():
        raise InputError("not a complete stream folder (no stream.json)", root)
    meta = load_json(path, "stream file")  # a FIFO, a device, nesting 100,000 deep: one line
    if not isinstance(meta, dict) or not isinstance(meta.get("sequences"), dict):
        raise InputError("malformed stream file (no 'sequences' object)", path)
    return meta, path


def read_sequence(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(times (N,) int64 µs, poses (N,4,4) sensor → world)`` of one sequence folder, of equal length."""
    times, poses = read_times(folder / "times.txt"), read_poses(folder / "poses.txt")
    if len(times) != len(poses):
        raise InputError(f"{len(poses)} poses but {len(times)} capture times", folder / "poses.txt")
    return times, poses


def frame_boxes(label_file: Path, calib_file: Path) -> tuple[np.ndarray, list[str]]:
    """Sensor-frame ``(N,7)`` boxes and names of a label file's objects (DontCare rows carry no 3D box and are left
    out); no file, no boxes."""
    if not label_file.is_file():
        return np.zeros((0, 7)), []
    objs = read_labels(label_file).objects()
    if len(objs) == 0:
        return np.zeros((0, 7)), []
    return labels_to_boxes(objs, read_calib(calib_file)), [str(n) for n in objs.names]


def dataset_frame_ids(root: Path, limit: int | None = None) -> list[str]:
    """The first ``limit`` (all: None) frame ids of a ``generate`` dataset, in order; no ``training/velodyne`` or no
    frame is an :class:`InputError`."""
    velodyne = root / "training" / "velodyne"
    if not velodyne.is_dir():
        raise InputError("not a KITTI-format dataset (no training/velodyne)", root)
    ids = sorted(p.stem for p in velodyne.glob("*.bin"))[:limit]
    if not ids:
        raise InputError("the dataset has no frames", velodyne)
    return ids
