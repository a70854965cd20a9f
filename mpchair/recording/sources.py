"""What both recorders (Rerun, ROS 2 / MCAP) and ``detector stream-eval`` read from a stream or dataset folder: the
stream's metadata (:func:`read_stream_meta`, the one check of ``stream.json`` every command shares), one sequence's
times and poses, one frame's boxes. Sensor frame (x forward, y left, z up), metres."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from mpchair.core.errors import InputError
from mpchair.core.text import load_json
from mpchair.geometry import labels_to_boxes
from mpchair.kitti import read_calib, read_labels, read_poses, read_times

#: Fastest sensor rate a stream may declare (Hz); real depth cameras and LiDARs run at 1-100 Hz.
MAX_RATE_HZ = 1000.0
#: Slowest sensor rate a stream may declare (Hz): one frame per ~17 minutes; below it a frame period overflows the
#: time stamps a recording writes (1e-300 Hz is a period of 1e300 s).
MIN_RATE_HZ = 1e-3


@dataclasses.dataclass(frozen=True)
class Region:
    """The labelled region of the stream's sensor (:mod:`mpchair.geometry.region`): metres, radians (``None``: no
    field-of-view limit)."""

    max_abs_dz: float
    max_distance: float
    half_fov: float | None


@dataclasses.dataclass(frozen=True, eq=False)
class StreamMeta:
    """A stream folder's checked ``stream.json``: its ``path``, the sensor ``rate_hz``, the labelled ``region``, the
    virtual camera's ``image_size`` (W, H) in pixels, the ``sequences`` names in order and the parsed file
    (``data``)."""

    path: Path
    rate_hz: float
    region: Region
    image_size: tuple[int, int]
    sequences: tuple[str, ...]
    data: dict


def read_stream_meta(root: Path) -> StreamMeta:
    """The checked ``stream.json`` of a stream folder (``mpchair stream``). Every command that reads a stream
    (``mpchair view --rerun / --mcap``, ``detector stream-eval``) calls this, so all refuse the same files: a missing,
    unreadable or malformed file, a ``rate_hz`` that is not a number in [:data:`MIN_RATE_HZ`, :data:`MAX_RATE_HZ`]
    Hz (0, 1e-300, NaN, 1e300), a region that is not positive and finite, an empty image size or no ``sequences``
    object is an :class:`InputError` naming the file."""
    root = Path(root)
    path = root / "stream.json"
    if not path.is_file():
        raise InputError("not a complete stream folder (no stream.json; run or finish `mpchair stream`)", root)
    meta = load_json(path, "stream file")  # a FIFO, a device, nesting 100,000 deep: one line
    if not isinstance(meta, dict) or not isinstance(meta.get("sequences"), dict):
        raise InputError("malformed stream file (no 'sequences' object)", path)
    try:
        r = meta["region"]
        region = Region(_number(r["max_abs_dz"]), _number(r["max_distance"]),
                        None if r["half_fov"] is None else _number(r["half_fov"]))
        size = (_whole(meta["image_size"][0]), _whole(meta["image_size"][1]))
        rate = _number(meta["rate_hz"])
    except (KeyError, IndexError, TypeError, ValueError, OverflowError) as e:
        raise InputError(f"malformed stream file ({type(e).__name__}: {' '.join(str(e).split())[:200]})",
                         path) from None
    if not (math.isfinite(rate) and MIN_RATE_HZ <= rate <= MAX_RATE_HZ):
        raise InputError(f"rate_hz: expected a sensor rate in [{MIN_RATE_HZ:g}, {MAX_RATE_HZ:g}] Hz, got {rate!r}",
                         path)
    fov = () if region.half_fov is None else (region.half_fov,)
    if not all(math.isfinite(v) and v > 0 for v in (region.max_abs_dz, region.max_distance, *fov)):
        raise InputError(f"region: expected positive finite limits, got {meta['region']!r}", path)
    if min(size) < 1:
        raise InputError(f"image_size: expected a positive width and height, got {list(size)}", path)
    odd = next((n for n in meta["sequences"] if not (n.isascii() and n.isdigit())), None)
    if odd is not None:  # a name is a folder under sequences/: "../x" would read files outside the stream
        raise InputError(f"sequences: expected names of digits (00, 01, ...), got {odd!r}", path)
    return StreamMeta(path=path, rate_hz=rate, region=region, image_size=size,
                      sequences=tuple(sorted(meta["sequences"])), data=meta)


def _number(value: object) -> float:
    """A JSON number as a float (``ValueError`` for anything else: a string such as ``"fast"``, a bool, a list)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"expected a number, got {value!r}")
    return float(value)


def _whole(value: object) -> int:
    """A JSON whole number as an int (``ValueError`` for anything else, 640.5 included)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != int(value):
        raise ValueError(f"expected a whole number, got {value!r}")
    return int(value)


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
