"""Rerun recordings (``.rrd``) of streams and datasets, for the Rerun viewer (``rerun OUT.rrd``).

Entities, in the house (world) frame, z up, metres:

* ``world/<seq>/sensor``: the sensor pose at each frame (a transform, sensor → world); its children are in the
  sensor frame: ``points`` (the scan), ``labels`` (kept chairs, green, named), ``dontcare`` (DontCare chairs, grey);
* ``world/<seq>/trajectory``: the whole path of the sensor (static);
* ``detector stream-eval --rerun`` adds ``world/<seq>/sensor/detections/{raw,ego}``: the boxes the detector had at
  that moment, as emitted (stale) and moved by the robot's motion.

Timelines: ``frame`` (index within the sequence) and ``time`` (capture time, seconds; streams only). A dataset made
by ``generate`` has no sequences: its frames are logged as ``world/frames`` in frame order.

Part of the shared floor (``docs/design.md``): it imports only ``mpchair.geometry`` and ``mpchair.kitti``, and
rerun-sdk, an optional extra, only when a recording is written.
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import os
import shutil
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from mpchair.core.atomic import atomic_path, check_writable, remove_dead_temps
from mpchair.core.errors import InputError
from mpchair.kitti import frame_paths, read_poses, read_velodyne
from mpchair.recording.sources import dataset_frame_ids, frame_boxes, read_sequence, read_stream_meta

#: How to get the optional dependency.
INSTALL_HINT = "install the rerun extra: pip install -e '.[rerun]' (rerun-sdk==0.41.0)"
GREEN, GREY, RED, BLUE = (40, 200, 80), (150, 150, 150), (230, 60, 50), (60, 120, 240)


def check_rerun_path(path: str | Path) -> None:
    """Fail early (:class:`InputError`) when ``path`` is not an ``.rrd`` file name or rerun-sdk is missing."""
    if Path(path).suffix.lower() != ".rrd":
        raise InputError("--rerun must name a .rrd file", path)
    check_writable(path)
    _rerun()


def _rerun():
    # rerun-sdk's Rust logger prints its own multi-line errors (a full disk) to stderr; this module turns every failure
    # into one OSError, so the logger stays quiet unless the user asks for it with RUST_LOG.
    os.environ.setdefault("RUST_LOG", "off")
    try:
        import rerun
    except ImportError:
        raise InputError(f"--rerun needs rerun-sdk, which is not installed; {INSTALL_HINT}") from None
    return rerun


#: Longest wait for rerun-sdk's file writer to catch up (seconds); it writes a frame in milliseconds on a healthy disk.
FLUSH_TIMEOUT_S = 10.0


class Recorder:
    """A recording written to the temporary file ``path`` (see :func:`recording`); ``out`` is the file name users see
    in errors. Each frame's data is flushed before the next frame starts, with a timeout, so a full disk surfaces as
    one ``OSError`` naming ``out`` within a frame, where rerun's writer thread would otherwise die (or, at the end,
    hang in ``flush``)."""

    def __init__(self, path: str | Path, application: str = "mpchair", out: str | Path | None = None):
        rr = self.rr = _rerun()
        self._tmp, self.out = Path(path), Path(out or path)
        self.rec = rr.RecordingStream(application)
        self.rec.save(str(path))
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.failed = False

    def time(self, frame: int, time_us: int | None = None) -> None:
        """Set the timelines for what is logged next (after flushing what came before): ``frame`` index and capture
        time (microseconds)."""
        self.flush()
        self.rec.set_time("frame", sequence=int(frame))
        if time_us is not None:
            self.rec.set_time("time", duration=int(time_us) * 1e-6)

    def flush(self) -> None:
        """Wait (at most :data:`FLUSH_TIMEOUT_S`) until everything logged is in the file; a write failure is an
        ``OSError`` naming ``out`` (``ENOSPC`` when the disk is full)."""
        try:
            self.rec.flush(timeout_sec=FLUSH_TIMEOUT_S)
        except Exception as e:  # rerun raises RuntimeError (its writer died) or TimeoutError; the cause is in its log
            self.failed = True
            raise write_error(e, self._tmp.parent, self.out, "write") from None

    def pose(self, entity: str, T: np.ndarray) -> None:
        """A (4,4) transform of ``entity`` into its parent's frame (child → parent)."""
        T = np.asarray(T, dtype=np.float64)
        self.rec.log(entity, self.rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))

    def points(self, entity: str, points: np.ndarray) -> None:
        """(N,3+) points in the parent entity's frame (metres)."""
        self.rec.log(entity, self.rr.Points3D(np.asarray(points)[:, :3], radii=0.01))

    def boxes(self, entity: str, boxes: np.ndarray, color: tuple[int, int, int], labels: list[str] | None = None,
              ) -> None:
        """(N,7) boxes ``[x, y, z, l, w, h, yaw]`` (geometric centre, yaw CCW about +z) in the parent entity's frame."""
        rr = self.rr
        b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
        angles = [rr.RotationAxisAngle(axis=[0.0, 0.0, 1.0], radians=float(y)) for y in b[:, 6]]
        self.rec.log(entity, rr.Boxes3D(centers=b[:, :3], half_sizes=b[:, 3:6] / 2, rotation_axis_angles=angles,
                                        colors=[color] * len(b), labels=labels))

    def path(self, entity: str, xyz: np.ndarray) -> None:
        """A static line through (K,3) world points."""
        self.rec.log(entity, self.rr.LineStrips3D([np.asarray(xyz, dtype=np.float64)], colors=[BLUE]), static=True)

    def close(self) -> None:
        """Write everything to the file and close it (``OSError`` as :meth:`flush`). A stream whose write failed is
        kept, untouched, until the process ends: its ``disconnect`` and its destructor wait on the dead writer
        thread forever (rerun-sdk 0.41), while rerun's own exit hook shuts it down cleanly."""
        if self.failed:
            _abandon(self.rec)
            return
        self.flush()
        self.rec.disconnect()


#: Recording streams whose file write failed, kept alive so that their destructor never runs (see Recorder.close).
_ABANDONED: list = []


def _abandon(stream) -> None:
    """Keep a failed stream until the process ends, and end the process without rerun's exit hook, which waits on
    the stream's blocked writer thread forever (seen on a full tmpfs). Only a failed write gets here, and it has
    become an ``OSError`` that the CLI reports with exit status 2, so the process ends with status 2."""
    if not _ABANDONED:
        atexit.register(_exit_now)  # atexit runs last-registered first: before rerun's hook
    _ABANDONED.append(stream)


def _exit_now() -> None:
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(2)


#: Free space below which a failed write is reported as a full disk (bytes).
MIN_FREE_BYTES = 1 << 20


def write_error(e: Exception, folder: Path, out: str | Path, what: str) -> OSError:
    """The one-line ``OSError`` naming ``out`` for rerun-sdk's failure ``e`` to ``what`` (start / write) a recording
    in ``folder``: ``ENOSPC`` when the disk is full, else ``EIO`` with rerun's words."""
    if shutil.disk_usage(folder).free < MIN_FREE_BYTES:
        return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(out))
    return OSError(errno.EIO, f"rerun-sdk could not {what} the recording ({' '.join(str(e).split())[:200]})", str(out))


@contextlib.contextmanager
def recording(out: str | Path) -> Iterator[Recorder]:
    """A :class:`Recorder` whose file appears at ``out`` only once the block has succeeded (``mpchair.core.atomic``:
    a failure, a full disk included, leaves neither the file nor a temporary)."""
    remove_dead_temps(out)  # what a killed recording of the same file left (up to 15 MB each)
    with atomic_path(out) as tmp:
        try:
            rec = Recorder(tmp, out=out)
        except RuntimeError as e:  # rerun-sdk cannot even write the file header (the disk is full already)
            raise write_error(e, Path(tmp).parent, out, "start") from None
        try:
            yield rec
        except BaseException:
            # The block failed (bad input, Ctrl-C, a failed write): end the stream; only a stream whose write failed
            # is abandoned (close), a healthy one is flushed and disconnected, and the block's error is what counts.
            with contextlib.suppress(OSError):
                rec.close()
            raise
        rec.close()


FrameHook = Callable[[Recorder, str, str, int], None]


def log_stream(root: str | Path, out: str | Path, extra: FrameHook | None = None) -> dict:
    """Write the stream folder ``root`` (``mpchair stream``) as a recording ``out``; ``extra(recorder, entity,
    sequence, i)`` may log more under ``entity`` (the sensor) for each frame. Returns ``{"sequences", "frames"}``."""
    root = Path(root)
    names = read_stream_meta(root).sequences  # checked as every stream reader checks it
    frames = 0
    with recording(out) as rec:
        for seq in names:
            frames += _log_sequence(rec, root / "sequences" / seq, seq, extra)
    return {"sequences": len(names), "frames": frames}


def _log_sequence(rec: Recorder, d: Path, seq: str, extra: FrameHook | None) -> int:
    """Log sequence ``seq`` of folder ``d``; returns its frame count."""
    times, poses = read_sequence(d)
    rec.path(f"world/{seq}/trajectory", poses[:, :3, 3])
    sensor = f"world/{seq}/sensor"
    for i in range(len(times)):
        fid = f"{i:06d}"
        rec.time(i, int(times[i]))
        rec.pose(sensor, poses[i])
        rec.points(f"{sensor}/points", read_velodyne(d / "velodyne" / f"{fid}.bin"))
        boxes, labels = frame_boxes(d / "label_2" / f"{fid}.txt", d / "calib" / f"{fid}.txt")
        rec.boxes(f"{sensor}/labels", boxes, GREEN, labels)
        dc, _ = frame_boxes(d / "label_dontcare" / f"{fid}.txt", d / "calib" / f"{fid}.txt")
        rec.boxes(f"{sensor}/dontcare", dc, GREY)
        if extra is not None:
            extra(rec, sensor, seq, i)
    return len(times)


def log_dataset(root: str | Path, out: str | Path, limit: int | None = None) -> dict:
    """Write the first ``limit`` frames (all: ``None``) of a ``generate`` dataset ``root`` as a recording ``out``:
    each frame's pose (``training/pose``), scan and labels under ``world/frames``. Returns ``{"frames"}``."""
    root = Path(root)
    ids = dataset_frame_ids(root, limit)
    sensor = "world/frames/sensor"
    with recording(out) as rec:
        for n, fid in enumerate(ids):
            paths = frame_paths(root, fid)
            rec.time(n)
            pose_file = root / "training" / "pose" / f"{fid}.txt"
            if pose_file.is_file():
                rec.pose(sensor, read_poses(pose_file)[0])
            rec.points(f"{sensor}/points", read_velodyne(paths.velodyne))
            boxes, labels = frame_boxes(paths.label_2, paths.calib)
            rec.boxes(f"{sensor}/labels", boxes, GREEN, labels)
    return {"frames": len(ids)}
