"""Read a stream folder written by ``mpchair stream``: its sequences, capture times, poses and per-frame labels.

Layout (``docs/streaming.md``): ``DIR/stream.json``; ``DIR/sequences/NN/{velodyne,label_2,label_dontcare,calib}/
NNNNNN.*``, ``times.txt`` (seconds, exact integer microseconds) and ``poses.txt`` (3x4 sensor → world, row-major).
Times are kept as int64 microseconds so that ``emitted <= captured`` comparisons are exact.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from mpchair.core.errors import InputError
from mpchair.kitti import Calib, Labels, read_calib, read_labels, read_poses, read_times
from mpchair.recording.sources import StreamMeta, read_stream_meta


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
    """A stream folder: its checked ``stream.json`` (``meta``: the sensor ``rate_hz``, the labelled ``region``, the
    virtual camera's ``image_size`` (W, H) in pixels, the parsed file) and its ``sequences`` in name order."""

    root: Path
    meta: StreamMeta
    sequences: tuple[StreamSequence, ...]

    @property
    def frames(self) -> int:
        """Frames over all sequences."""
        return sum(len(s) for s in self.sequences)


def read_stream(root: str | Path) -> Stream:
    """Read ``stream.json`` (checked by :func:`mpchair.recording.sources.read_stream_meta`, as ``mpchair view`` checks
    it) and every sequence's times and poses; a missing or inconsistent file is an :class:`InputError` naming it."""
    root = Path(root)
    meta = read_stream_meta(root)
    seqs = []
    for name in meta.sequences:
        folder = root / "sequences" / name
        times = read_times(folder / "times.txt")
        poses = read_poses(folder / "poses.txt")
        if len(poses) != len(times):
            raise InputError(f"{len(poses)} poses but {len(times)} capture times", folder / "poses.txt")
        seqs.append(StreamSequence(name, folder, times, poses))
    if not seqs:
        raise InputError("the stream has no sequences", meta.path)
    return Stream(root=root, meta=meta, sequences=tuple(seqs))
