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
    .frames/NN/NNNNNN.json                  per-frame record (StreamFrameRecord); a frame is done iff its record
                                            exists (written last)
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from mpchair.core.atomic import write_text
from mpchair.core.errors import InputError
from mpchair.dataset.frame import box_labels, calib_text, dontcare_candidates, frame_labels, kitti_name
from mpchair.kitti import write_labels, write_poses, write_times, write_velodyne
from mpchair.labels.select import BoxDecisions
from mpchair.matterport.house import House
from mpchair.scan.sensors import SensorConfig, camera_calib

#: Per-frame folders of a sequence.
FRAME_DIRS = ("velodyne", "label_2", "label_dontcare", "calib")


@dataclasses.dataclass(frozen=True)
class StreamFrameRecord:
    """One frame of a stream, what ``.frames/<sequence>/<frame>.json`` holds: its ``sequence`` and ``frame`` ids, the
    capture time ``time_us`` (integer microseconds from the sequence start), ``points`` in the scan, ``rays`` cast,
    boxes ``kept`` and ``dontcare`` (rejected inside the labelled region), ``rejected`` boxes by reason."""

    sequence: str
    frame: str
    time_us: int
    points: int
    rays: int
    kept: int
    dontcare: int
    rejected: dict[str, int]

    def to_dict(self) -> dict[str, Any]:
        """The record as JSON data."""
        return dataclasses.asdict(self)

    def to_json(self) -> str:
        """The record's file text without its newline: one line, sorted keys."""
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> StreamFrameRecord:
        """The record of :meth:`to_dict`'s data (a missing key is a ``KeyError``)."""
        return cls(sequence=data["sequence"], frame=data["frame"], time_us=data["time_us"], points=data["points"],
                   rays=data["rays"], kept=data["kept"], dontcare=data["dontcare"], rejected=dict(data["rejected"]))


def read_stream_record(path: str | Path) -> StreamFrameRecord:
    """The :class:`StreamFrameRecord` in ``path``; a file that does not hold one is an :class:`InputError` naming
    it."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
        return StreamFrameRecord.from_dict(data)
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError, AttributeError) as e:
        why = f"missing key {e}" if isinstance(e, KeyError) else str(e)
        raise InputError(f"not an mpchair stream frame record: {why}", path) from None


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
                       sensor: SensorConfig, time_us: int, rays: int) -> StreamFrameRecord:
    """Write frame ``fid`` of sequence ``seq`` (velodyne, label_2, label_dontcare, calib), then its record (last).

    ``decisions`` after every filter (scan points included), ``points`` (M,4) float32 sensor frame. Returns the
    record.
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
    record = StreamFrameRecord(sequence=seq, frame=fid, time_us=int(time_us), points=len(points), rays=int(rays),
                               kept=int(decisions.kept.sum()), dontcare=len(ignored), rejected=rejected)
    write_text(record_path(out, seq, fid), record.to_json() + "\n")
    return record
