"""Ground-truth database and GT sampling ("copy-paste" augmentation, as in SECOND / OpenPCDet / Open3D-ML).

:func:`build_gt_database` cuts every training object's points out of the training frames, in the frame it came from
(sensor frame, metres). :func:`sample_ground_truth` tops a scene up to a per-class object count by pasting database
objects at their original place: a candidate whose BEV rectangle overlaps any box already in the scene (or an earlier
pasted one) is skipped, and scene points inside an accepted box are removed before its own points go in, so each
pasted box holds exactly its own points plus nothing of the scene.
"""

from __future__ import annotations

import dataclasses
import io
import json
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from mpchair.core.atomic import atomic_open
from mpchair.core.errors import InputError
from mpchair.geometry import bev_polygons, points_in_boxes

_FORMAT = 1  # bump when the file layout changes


@dataclasses.dataclass(frozen=True, eq=False)
class GTDatabase:
    """Objects cut out of training frames, as parallel arrays of length E.

    ``names`` (E,) class names; ``boxes`` (E,7) float64 sensor-frame boxes of the source frame; ``frame_ids`` (E,)
    source frame ids; ``offsets`` (E+1,) int64: object ``e`` owns ``points[offsets[e]:offsets[e+1]]``; ``points``
    (P,C) float32 in the source frame's sensor coordinates (the object is pasted where it was). ``meta`` records what
    the database was built from (compared when a cached file is reused).
    """

    names: np.ndarray
    boxes: np.ndarray
    frame_ids: np.ndarray
    offsets: np.ndarray
    points: np.ndarray
    meta: dict = dataclasses.field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.names)

    @property
    def num_points(self) -> np.ndarray:
        """(E,) int64 points per object."""
        return np.diff(self.offsets)

    def object_points(self, index: int) -> np.ndarray:
        """(K,C) float32 points of object ``index``."""
        return self.points[self.offsets[index] : self.offsets[index + 1]]

    def candidates(self, name: str, min_points: int = 0) -> np.ndarray:
        """(K,) int64 indices of the objects of class ``name`` with at least ``min_points`` points."""
        return np.flatnonzero((self.names == name) & (self.num_points >= min_points))

    def save(self, path: str | Path) -> None:
        """Write the database atomically as an ``.npz`` file."""
        buf = io.BytesIO()
        np.savez(
            buf,
            format=np.int64(_FORMAT),
            names=self.names.astype(str),
            boxes=self.boxes,
            frame_ids=self.frame_ids.astype(str),
            offsets=self.offsets,
            points=self.points,
            meta=np.array(json.dumps(self.meta, sort_keys=True)),
        )
        with atomic_open(path, "wb") as f:
            f.write(buf.getvalue())

    @classmethod
    def load(cls, path: str | Path) -> GTDatabase:
        """Read a database written by :meth:`save`; a damaged or foreign file is an :class:`InputError`."""
        try:
            with np.load(path, allow_pickle=False) as z:
                if int(z["format"]) != _FORMAT:
                    raise InputError(f"GT database format {int(z['format'])} is not {_FORMAT}", path)
                return cls(
                    names=z["names"],
                    boxes=z["boxes"],
                    frame_ids=z["frame_ids"],
                    offsets=z["offsets"],
                    points=z["points"],
                    meta=json.loads(str(z["meta"])),
                )
        except (OSError, KeyError, ValueError) as e:
            raise InputError(f"cannot read GT database: {e}", path) from None


def build_gt_database(frames: Iterable, *, meta: Mapping | None = None, progress: bool = False) -> GTDatabase:
    """Collect every object of ``frames`` (an iterable of :class:`detector.data.Frame`, e.g. a ``KittiDataset``).

    Each object keeps the points that lie inside (or on a face of) its box, in its frame's sensor coordinates. Objects
    with zero points are kept too (``min_points`` filters them at sampling time).
    """
    names: list[np.ndarray] = []
    boxes: list[np.ndarray] = []
    frame_ids: list[str] = []
    parts: list[np.ndarray] = []
    counts: list[int] = []
    channels = None
    for frame in tqdm(frames, desc="GT database", unit="frame", disable=not progress, leave=False):
        channels = frame.points.shape[1]
        if not len(frame.boxes):
            continue
        inside = points_in_boxes(frame.points, frame.boxes)
        for k in range(len(frame.boxes)):
            pts = frame.points[inside[k]]
            parts.append(pts)
            counts.append(len(pts))
            frame_ids.append(frame.frame_id)
        names.append(frame.names)
        boxes.append(frame.boxes)
    channels = channels or 4
    return GTDatabase(
        names=np.concatenate(names).astype(str) if names else np.zeros(0, dtype=str),
        boxes=np.concatenate(boxes).astype(np.float64) if boxes else np.zeros((0, 7)),
        frame_ids=np.array(frame_ids, dtype=str),
        offsets=np.concatenate([[0], np.cumsum(counts, dtype=np.int64)]).astype(np.int64),
        points=np.concatenate(parts).astype(np.float32) if parts else np.zeros((0, channels), dtype=np.float32),
        meta=dict(meta or {}),
    )


def bev_boxes_overlap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,M) bool: the BEV rectangles of boxes ``a`` (N,7) and ``b`` (M,7) share area (same frame, metres).

    Exact separating-axis test for two rectangles: they are disjoint iff their projections onto one of the four edge
    directions do not overlap. Rectangles that only touch along an edge or a corner count as disjoint.
    """
    a = np.asarray(a, dtype=np.float64).reshape(-1, 7)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 7)
    if not len(a) or not len(b):
        return np.zeros((len(a), len(b)), dtype=bool)
    ca, cb = bev_polygons(a), bev_polygons(b)  # (N,4,2), (M,4,2)

    def axes(boxes: np.ndarray) -> np.ndarray:
        c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
        return np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], 1)  # (K,2,2) unit edge directions

    n, m = len(a), len(b)
    ax = np.concatenate(
        [np.broadcast_to(axes(a)[:, None], (n, m, 2, 2)), np.broadcast_to(axes(b)[None], (n, m, 2, 2))], axis=2
    )  # (N,M,4,2)
    pa = np.einsum("ncd,nmkd->nmkc", ca, ax)  # (N,M,4 axes,4 corners)
    pb = np.einsum("mcd,nmkd->nmkc", cb, ax)
    separated = (pa.max(-1) <= pb.min(-1)) | (pb.max(-1) <= pa.min(-1))  # (N,M,4)
    return ~separated.any(-1)


@dataclasses.dataclass(frozen=True, eq=False)
class PasteResult:
    """A scene after GT sampling: ``points`` (N',C), ``boxes`` (M',7), ``labels`` (M',) and how many were pasted.

    Pasted objects come after the scene's own boxes; their points come first in ``points`` (the scene's follow).
    """

    points: np.ndarray
    boxes: np.ndarray
    labels: np.ndarray
    num_pasted: int


def sample_ground_truth(
    points: np.ndarray,
    boxes: np.ndarray,
    labels: np.ndarray,
    *,
    database: GTDatabase,
    classes: Sequence[str],
    sample_counts: Mapping[str, int],
    min_points: Mapping[str, int],
    rng: np.random.Generator,
    obstacles: np.ndarray | None = None,
) -> PasteResult:
    """Paste database objects into one scene (all arrays in the sensor frame, metres).

    For class ``c`` (index into ``classes``) the scene is topped up to ``sample_counts[c]`` objects: that many minus
    the scene's own boxes of ``c`` candidates with at least ``min_points[c]`` points are drawn without replacement
    from ``database``, then accepted greedily in draw order unless their BEV rectangle overlaps a scene box, an
    ``obstacles`` box (e.g. objects of other classes) or an already accepted box. Scene points inside accepted boxes
    are removed. ``points`` (N,C) float32, ``boxes`` (M,7), ``labels`` (M,) int64.
    """
    occupied = [np.asarray(boxes, dtype=np.float64).reshape(-1, 7)]
    if obstacles is not None:
        occupied.append(np.asarray(obstacles, dtype=np.float64).reshape(-1, 7))
    occupied_boxes = np.concatenate(occupied)
    accepted: list[int] = []
    accepted_labels: list[int] = []
    for ci, name in enumerate(classes):
        want = int(sample_counts.get(name, 0)) - int(np.sum(labels == ci))
        if want <= 0:
            continue
        pool = database.candidates(name, int(min_points.get(name, 0)))
        if not len(pool):
            continue
        draw = rng.choice(pool, size=min(want, len(pool)), replace=False)
        hits = bev_boxes_overlap(database.boxes[draw], occupied_boxes).any(1)
        inner = bev_boxes_overlap(database.boxes[draw], database.boxes[draw])
        taken: list[int] = []
        for j in range(len(draw)):
            if hits[j] or any(inner[j, t] for t in taken):
                continue
            taken.append(j)
        accepted.extend(int(draw[j]) for j in taken)
        accepted_labels.extend([ci] * len(taken))
        if taken:
            occupied_boxes = np.concatenate([occupied_boxes, database.boxes[draw[taken]]])
    if not accepted:
        return PasteResult(points, np.asarray(boxes).reshape(-1, 7), np.asarray(labels, dtype=np.int64), 0)
    new_boxes = database.boxes[accepted]
    scene_keep = ~points_in_boxes(points, new_boxes).any(0)
    pasted = [database.object_points(e)[:, : points.shape[1]] for e in accepted]
    out_points = np.concatenate([*pasted, points[scene_keep]]).astype(np.float32, copy=False)
    out_boxes = np.concatenate([np.asarray(boxes, dtype=np.float64).reshape(-1, 7), new_boxes])
    out_labels = np.concatenate([np.asarray(labels, dtype=np.int64), np.array(accepted_labels, dtype=np.int64)])
    return PasteResult(out_points, out_boxes, out_labels, len(accepted))
