"""ROS 2 bags (``.mcap``) of streams and datasets, written without a ROS install: MCAP files with the ``ros2`` profile,
``ros2msg`` schemas and ``cdr`` messages, as rosbag2's mcap storage writes them, so Foxglove opens them and
``ros2 bag play -s mcap OUT.mcap`` replays them.

Topics (frames REP 103: x forward, y left, z up, metres; our sensor frame already is):

* ``/points`` sensor_msgs/PointCloud2: the scan (``x, y, z, intensity`` float32, the velodyne file's bytes), frame
  ``sensor``;
* ``/tf`` tf2_msgs/TFMessage: ``world`` → ``base_link`` (the sensor's floor point and heading) → ``sensor``, from
  ``poses.txt`` (a dataset: each frame's ``training/pose`` file; none without it);
* ``/ground_truth`` vision_msgs/Detection3DArray: the labelled boxes in frame ``sensor`` (class = label type, score 1;
  a stream's DontCare boxes with class ``DontCare``), and ``/ground_truth/markers`` visualization_msgs/MarkerArray,
  the same boxes as wireframes with their names (green; DontCare grey), since RViz cannot draw Detection3DArray;
* ``/trajectory`` nav_msgs/Path (streams only): a sequence's whole path in ``world``, once, at its first frame;
* ``detector stream-eval --mcap`` adds ``/detections/<model>`` and ``/detections/<model>/ego`` (see
  ``detector.stream.mcap``).

Stamps (header and log time alike) are the capture times of ``times.txt``; a stream's sequences follow each other,
each starting one frame period after the previous one ended (the offsets are in the file's ``mpchair`` metadata
record). A dataset's frames are ``1 / rate`` apart (10 Hz by default). One message per frame on every topic but
``/trajectory``. With the same inputs the file is the same bytes.

Part of the shared floor (``docs/design.md``): it imports only ``mpchair.core``, ``mpchair.geometry`` and
``mpchair.kitti``, and mcap + mcap-ros2-support, an optional extra (``ros``), only when a bag is written.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import BinaryIO

import numpy as np

from mpchair.core.atomic import atomic_open, remove_dead_temps
from mpchair.core.errors import InputError
from mpchair.geometry import invert_rigid, yaw_matrix
from mpchair.kitti import frame_paths, read_poses, read_velodyne
from mpchair.recording import ros2_convert as msg
from mpchair.recording.ros2_msgs import schema_text
from mpchair.recording.sources import dataset_frame_ids, frame_boxes, read_sequence, read_stream_meta

#: How to get the optional dependency.
INSTALL_HINT = "install the ros extra: pip install -e '.[ros]' (mcap==1.6.0, mcap-ros2-support==0.6.0)"
POINTS, TF, GROUND_TRUTH, TRAJECTORY = "/points", "/tf", "/ground_truth", "/trajectory"
#: Suffix of the MarkerArray topic beside each Detection3DArray topic.
MARKERS = "/markers"
WORLD, BASE_LINK, SENSOR = "world", "base_link", "sensor"
LABEL_COLOR, DONTCARE_COLOR = (40, 200, 80), (150, 150, 150)
#: A dataset's frames have no capture times: they are played at this rate by default (Hz).
DATASET_RATE_HZ = 10.0
#: Name of the MCAP metadata record that says what the bag holds.
METADATA_NAME = "mpchair"


def check_mcap_path(path: str | Path) -> None:
    """Fail early (:class:`InputError`) when ``path`` is not a ``.mcap`` file name, cannot be created (a folder, or
    below a file or an unwritable folder) or mcap-ros2-support is missing."""
    path = Path(path)
    if path.suffix.lower() != ".mcap":
        raise InputError("--mcap must name a .mcap file", path)
    if path.is_dir():
        raise InputError("--mcap names a folder; give a .mcap file name", path)
    parent = path.absolute().parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise InputError("cannot write the bag here: not a folder", parent)
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError("cannot write the bag here: the folder is not writable", parent)
    _ros2_writer()


def _ros2_writer():
    """mcap-ros2-support's writer class, or the one-line error naming the extra."""
    try:
        from mcap_ros2.writer import Writer
    except ImportError:
        raise InputError(f"--mcap needs mcap and mcap-ros2-support, which are not installed; {INSTALL_HINT}") from None
    return Writer


class Bag:
    """An MCAP file of ROS 2 messages written to the binary file object ``f`` (see :func:`bag_file`): schemas are
    registered on first use, one channel per topic; ``counts`` is the number of messages per topic."""

    def __init__(self, f: BinaryIO):
        # chunked and zstd-compressed with message indexes (the library's defaults), which rosbag2 and Foxglove read
        self._writer = _ros2_writer()(f)
        self._schemas: dict[str, object] = {}
        self._types: dict[str, str] = {}
        self.counts: Counter = Counter()

    def write(self, topic: str, type_name: str, message: dict, time_us: int) -> None:
        """Write ``message`` of type ``type_name`` (``pkg/msg/Type``) on ``topic``, logged and published at
        ``time_us`` (integer microseconds)."""
        if self._types.setdefault(topic, type_name) != type_name:
            raise ValueError(f"topic {topic} carries {self._types[topic]}, not {type_name}")
        schema = self._schemas.get(type_name)
        if schema is None:
            schema = self._schemas[type_name] = self._writer.register_msgdef(type_name, schema_text(type_name))
        ns = int(time_us) * 1000
        self._writer.write_message(topic, schema, message, log_time=ns, publish_time=ns)
        self.counts[topic] += 1

    def metadata(self, name: str, data: dict[str, str]) -> None:
        """An MCAP metadata record (string keys and values)."""
        self._writer.add_metadata(name, data)

    def close(self) -> None:
        """Write the summary section (indexes, statistics) and the footer."""
        self._writer.finish()


@contextlib.contextmanager
def bag_file(out: str | Path) -> Iterator[Bag]:
    """A :class:`Bag` whose file appears at ``out`` only once the block has succeeded (``mpchair.core.atomic``)."""
    remove_dead_temps(out)  # what a killed recording of the same file left
    with atomic_open(out, "wb") as f:
        bag = Bag(f)
        yield bag
        bag.close()


def write_boxes(bag: Bag, topic: str, boxes: np.ndarray, names: Sequence[str], scores: Sequence[float],
                colors: Sequence[tuple[int, int, int]], texts: Sequence[str] | None, time_us: int) -> None:
    """(N,7) sensor-frame boxes as a Detection3DArray on ``topic`` and a MarkerArray on ``topic + MARKERS``."""
    bag.write(topic, "vision_msgs/msg/Detection3DArray", msg.detections(boxes, names, scores, time_us, SENSOR),
              time_us)
    bag.write(topic + MARKERS, "visualization_msgs/msg/MarkerArray",
              msg.markers(boxes, colors, texts, time_us, SENSOR), time_us)


def base_link_pose(T: np.ndarray, height: float) -> np.ndarray:
    """(4,4) base_link → world of a (4,4) sensor → world pose: ``height`` metres straight below the sensor, turned to
    the sensor's heading (its x axis seen from above), upright."""
    T = np.asarray(T, dtype=np.float64)
    B = yaw_matrix(float(np.arctan2(T[1, 0], T[0, 0])))
    B[:3, 3] = T[:3, 3] - [0.0, 0.0, height]
    return B


def _tf(bag: Bag, T: np.ndarray, height: float, time_us: int) -> None:
    """``/tf``: world → base_link → sensor, composing exactly to the sensor pose ``T`` (sensor → world)."""
    B = base_link_pose(T, height)
    bag.write(TF, "tf2_msgs/msg/TFMessage", {"transforms": [
        msg.transform(B, time_us, WORLD, BASE_LINK),
        msg.transform(invert_rigid(B) @ T, time_us, BASE_LINK, SENSOR)]}, time_us)


def _log_frame(bag: Bag, velodyne: Path, label: Path, calib: Path, dontcare: Path | None, pose: np.ndarray | None,
               height: float, time_us: int) -> None:
    """One frame's ``/tf`` (with a pose), ``/points`` and ``/ground_truth`` (+ markers)."""
    if pose is not None:
        _tf(bag, pose, height, time_us)
    bag.write(POINTS, "sensor_msgs/msg/PointCloud2", msg.point_cloud(read_velodyne(velodyne), time_us, SENSOR),
              time_us)
    boxes, names = frame_boxes(label, calib)
    dc = frame_boxes(dontcare, calib)[0] if dontcare is not None else np.zeros((0, 7))
    colors = [LABEL_COLOR] * len(boxes) + [DONTCARE_COLOR] * len(dc)
    write_boxes(bag, GROUND_TRUTH, np.vstack([boxes, dc]), names + ["DontCare"] * len(dc),
                [1.0] * len(colors), colors, names + [""] * len(dc), time_us)


def _json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"malformed JSON ({type(e).__name__})", path) from None
    if not isinstance(data, dict):
        raise InputError("malformed JSON (not an object)", path)
    return data


def _sensor_height(meta: dict, path: Path) -> float:
    """The sensor height above the floor (metres) of a stream.json / manifest.json (``config.viewpoints.height``);
    0 (base_link at the sensor) when the file has no ``config``."""
    config = meta.get("config")
    if config is None:
        return 0.0
    viewpoints = config.get("viewpoints") if isinstance(config, dict) else None
    height = viewpoints.get("height") if isinstance(viewpoints, dict) else None
    if isinstance(height, bool) or not isinstance(height, (int, float)) or not 0 <= height < float("inf"):
        raise InputError(f"config.viewpoints.height: expected the sensor height above the floor in metres, got "
                         f"{height!r}", path)
    return float(height)


def _period_us(rate_hz: float, what: str) -> int:
    if isinstance(rate_hz, bool) or not isinstance(rate_hz, (int, float)) or not 0 < rate_hz < float("inf"):
        raise InputError(f"{what} must be a positive number of frames per second, got {rate_hz!r}")
    return max(1, round(1e6 / rate_hz))


#: ``extra(bag, sequence, i, time_us)`` may write more for frame ``i`` of ``sequence`` at its stamp.
FrameHook = Callable[[Bag, str, int, int], None]


def log_stream(root: str | Path, out: str | Path, extra: FrameHook | None = None) -> dict:
    """Write the stream folder ``root`` (``mpchair stream``) as the bag ``out``; ``extra`` may add messages for each
    frame. Returns ``{"sequences", "frames", "topics": {topic: messages}}``."""
    root = Path(root)
    meta = read_stream_meta(root)  # checked as every stream reader checks it (rate_hz in range, ...)
    names = meta.sequences
    period = _period_us(meta.rate_hz, "rate_hz")
    height = _sensor_height(meta.data, meta.path)
    frames, offset, offsets = 0, 0, {}
    with bag_file(out) as bag:
        for seq in names:
            offsets[seq] = offset
            n, end = _log_sequence(bag, root / "sequences" / seq, seq, offset, height, extra)
            frames += n
            offset = end + period
        bag.metadata(METADATA_NAME, {"kind": "stream", "rate_hz": str(meta.data["rate_hz"]),
                                     "sequence_offsets_us": json.dumps(offsets, sort_keys=True)})
    return {"sequences": len(names), "frames": frames, "topics": dict(sorted(bag.counts.items()))}


def _log_sequence(bag: Bag, d: Path, seq: str, offset_us: int, height: float, extra: FrameHook | None,
                  ) -> tuple[int, int]:
    """Write sequence ``seq`` of folder ``d`` with its times shifted by ``offset_us``; returns its frame count and its
    last stamp (microseconds)."""
    times, poses = read_sequence(d)
    stamps = [int(t) + offset_us for t in times]
    bag.write(TRAJECTORY, "nav_msgs/msg/Path", msg.path(poses, stamps, WORLD), stamps[0])
    for i, t in enumerate(stamps):
        fid = f"{i:06d}"
        _log_frame(bag, d / "velodyne" / f"{fid}.bin", d / "label_2" / f"{fid}.txt", d / "calib" / f"{fid}.txt",
                   d / "label_dontcare" / f"{fid}.txt", poses[i], height, t)
        if extra is not None:
            extra(bag, seq, i, t)
    return len(stamps), stamps[-1]


def log_dataset(root: str | Path, out: str | Path, limit: int | None = None, rate_hz: float = DATASET_RATE_HZ,
                ) -> dict:
    """Write the first ``limit`` frames (all: ``None``) of a ``generate`` dataset ``root`` as the bag ``out``, in frame
    order ``1 / rate_hz`` seconds apart from 0: each frame's ``/tf`` (from ``training/pose``, where there is one),
    ``/points`` and ``/ground_truth``. Returns ``{"frames", "topics": {topic: messages}}``."""
    root = Path(root)
    period = _period_us(rate_hz, "--rate")
    ids = dataset_frame_ids(root, limit)
    manifest = root / "manifest.json"
    height = _sensor_height(_json(manifest), manifest) if manifest.is_file() else 0.0
    with bag_file(out) as bag:
        for n, fid in enumerate(ids):
            paths = frame_paths(root, fid)
            pose_file = root / "training" / "pose" / f"{fid}.txt"
            pose = read_poses(pose_file)[0] if pose_file.is_file() else None
            _log_frame(bag, paths.velodyne, paths.label_2, paths.calib, None, pose, height, n * period)
        bag.metadata(METADATA_NAME, {"kind": "dataset", "period_us": str(period), "frame_ids": json.dumps(ids)})
    return {"frames": len(ids), "topics": dict(sorted(bag.counts.items()))}
