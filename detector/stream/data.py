"""Read a stream folder written by ``mpchair stream``: its sequences, capture times, poses and per-frame labels.

Layout (``docs/streaming.md``): ``DIR/stream.json``; ``DIR/sequences/NN/{velodyne,label_2,label_dontcare,calib}/
NNNNNN.*``, ``times.txt`` (seconds, exact integer microseconds) and ``poses.txt`` (3x4 sensor → world, row-major).
Times are kept as int64 microseconds so that ``emitted <= captured`` comparisons are exact.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from mpchair.core.errors import InputError
from mpchair.core.text import load_json
from mpchair.kitti import Calib, Labels, read_calib, read_labels, read_poses, read_times


@dataclasses.dataclass(frozen=True)
class Region:
    """The labelled region of the stream's sensor (:mod:`mpchair.geometry.region`): metres, radians (``None``: no
    field-of-view limit)."""

    max_abs_dz: float
    max_distance: float
    half_fov: float | None


@dataclasses.dataclass(frozen=True, eq=False)
class StreamSequence:
    """One sequence: ``name`` (``"00"``), its folder, capture ``times_us`` (N,) int64 and ``poses`` (N,4,4) sensor →
    world."""

    name: str
    folder: Path
    times_us: np.ndarray
    poses: np.ndarray

    def __len__(self) -> int:
        return len(self.times_us)

    def frame_id(self, i: int) -> str:
        """The 6-digit id of frame ``i``."""
        return f"{i:06d}"

    def labels(self, i: int) -> Labels:
        """``label_2`` of frame ``i`` (kept objects and DontCare rows; rectified camera frame)."""
        return read_labels(self.folder / "label_2" / f"{i:06d}.txt")

    def dontcare(self, i: int) -> Labels:
        """``label_dontcare`` of frame ``i``: the 3D boxes of its DontCare objects (rectified camera frame)."""
        return read_labels(self.folder / "label_dontcare" / f"{i:06d}.txt")

    def calib(self, i: int) -> Calib:
        """``calib`` of frame ``i``."""
        return read_calib(self.folder / "calib" / f"{i:06d}.txt")


@dataclasses.dataclass(frozen=True, eq=False)
class Stream:
    """A stream folder: ``rate_hz``, the labelled ``region``, image ``image_size`` (W, H) of the virtual camera,
    ``sequences`` in name order and the parsed ``stream.json`` (``meta``)."""

    root: Path
    rate_hz: float
    region: Region
    image_size: tuple[int, int]
    sequences: tuple[StreamSequence, ...]
    meta: dict

    @property
    def frames(self) -> int:
        """Frames over all sequences."""
        return sum(len(s) for s in self.sequences)


#: Fastest sensor rate a stream may declare (Hz); real depth cameras and LiDARs run at 1-100 Hz.
MAX_RATE_HZ = 1000.0


def read_stream(root: str | Path) -> Stream:
    """Read ``stream.json`` and every sequence's times and poses; a missing or inconsistent file is an
    :class:`InputError` naming it."""
    root = Path(root)
    meta_path = root / "stream.json"
    if not meta_path.is_file():
        raise InputError("not a complete stream folder (no stream.json; run or finish `mpchair stream`)", root)
    meta = load_json(meta_path, "stream file")  # a FIFO, a device, nesting 100,000 deep: one line
    try:
        region = Region(float(meta["region"]["max_abs_dz"]), float(meta["region"]["max_distance"]),
                        None if meta["region"]["half_fov"] is None else float(meta["region"]["half_fov"]))
        size = (int(meta["image_size"][0]), int(meta["image_size"][1]))
        names = sorted(meta["sequences"])
        rate = float(meta["rate_hz"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError, UnicodeDecodeError) as e:
        raise InputError(f"malformed stream file ({type(e).__name__}: {' '.join(str(e).split())[:200]})",
                         meta_path) from None
    if not (math.isfinite(rate) and 0 < rate <= MAX_RATE_HZ):
        raise InputError(f"rate_hz: expected a sensor rate in (0, {MAX_RATE_HZ:g}] Hz, got {rate!r}", meta_path)
    fov = () if region.half_fov is None else (region.half_fov,)
    if not all(math.isfinite(v) and v > 0 for v in (region.max_abs_dz, region.max_distance, *fov)):
        raise InputError(f"region: expected positive finite limits, got {meta['region']!r}", meta_path)
    if min(size) < 1:
        raise InputError(f"image_size: expected a positive width and height, got {list(size)}", meta_path)
    seqs = []
    for name in names:
        folder = root / "sequences" / name
        times = read_times(folder / "times.txt")
        poses = read_poses(folder / "poses.txt")
        if len(poses) != len(times):
            raise InputError(f"{len(poses)} poses but {len(times)} capture times", folder / "poses.txt")
        seqs.append(StreamSequence(name, folder, times, poses))
    if not seqs:
        raise InputError("the stream has no sequences", meta_path)
    return Stream(root=root, rate_hz=rate, region=region, image_size=size, sequences=tuple(seqs), meta=meta)
