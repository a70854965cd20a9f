"""The records a dataset folder holds about itself: one :class:`FrameRecord` per frame (``.frames/NNNNNN.json``, and
the ``frames`` list of the manifest) and the :class:`Manifest` (``manifest.json``, written last).

Both are plain JSON data, no paths and no times, so the same seed gives the same bytes. ``to_json()`` gives the text a
file holds (the writer adds one newline); :func:`read_frame_record` and :func:`read_manifest` read the files back
(a file that does not hold such a record is an :class:`~mpchair.core.errors.InputError` naming it). Boxes are in the
sensor frame (x forward, y left, z up, metres), poses map sensor → world (Matterport, z up, metres).

This module only describes the records (JSON in and out, counts over them): it imports no raycaster or mesh code, so
``mpchair stats`` and ``mpchair view`` read a manifest without loading the generator.
"""

from __future__ import annotations

import dataclasses
import json
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mpchair.core.errors import InputError

MANIFEST_FORMAT = "mpchair-kitti/1"
MANIFEST_NAME = "manifest.json"


@dataclasses.dataclass(frozen=True)
class KeptBox:
    """A labelled box of one frame: the house object (``object_index`` its O index, ``object_id`` habitat's id,
    ``class_name`` its mpcat40 name), ``box`` ``[x, y, z, l, w, h, yaw]`` (sensor frame, metres / radians, 6
    decimals), the dense-visibility counts (``visible_pixels``, ``points_in_box``, ``in_box_fraction``;
    ``visibility`` ``"exact"`` or ``"lower_bound"`` when a coarse subset of the grid already proved the box passes),
    ``scan_points`` (points of the stored scan inside the box), ``visible_fraction`` and the KITTI ``occluded``
    level."""

    object_index: int
    object_id: str
    class_name: str
    box: tuple[float | None, ...]
    visible_pixels: int
    points_in_box: int
    in_box_fraction: float | None
    visibility: str
    scan_points: int
    visible_fraction: float | None
    occluded: int

    def to_dict(self) -> dict[str, Any]:
        """The box as JSON data (the manifest's keys)."""
        return {"object": self.object_index, "id": self.object_id, "class": self.class_name, "box": list(self.box),
                "visible_pixels": self.visible_pixels, "points_in_box": self.points_in_box,
                "in_box_fraction": self.in_box_fraction, "visibility": self.visibility,
                "scan_points": self.scan_points, "visible_fraction": self.visible_fraction,
                "occluded": self.occluded}  # fmt: skip

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> KeptBox:
        """The box of :meth:`to_dict`'s data (a missing key is a ``KeyError``)."""
        return cls(object_index=data["object"], object_id=data["id"], class_name=data["class"],
                   box=tuple(data["box"]), visible_pixels=data["visible_pixels"],
                   points_in_box=data["points_in_box"], in_box_fraction=data["in_box_fraction"],
                   visibility=data["visibility"], scan_points=data["scan_points"],
                   visible_fraction=data["visible_fraction"], occluded=data["occluded"])  # fmt: skip


@dataclasses.dataclass(frozen=True)
class RejectedBox:
    """A box of the classes the filters rejected: the house object (as :class:`KeptBox`), the ``reason`` (the first
    filter it failed, :data:`mpchair.labels.filters.OUTSIDE_REGION_REASONS` and the visibility filters), and when
    the dense visibility was measured its ``visible_pixels`` and ``points_in_box`` (``None``: not measured, and then
    not in the JSON)."""

    object_index: int
    object_id: str
    class_name: str
    reason: str
    visible_pixels: int | None = None
    points_in_box: int | None = None

    def to_dict(self) -> dict[str, Any]:
        """The box as JSON data (the manifest's keys; the counts only when measured)."""
        out: dict[str, Any] = {"object": self.object_index, "id": self.object_id, "class": self.class_name,
                               "reason": self.reason}
        if self.visible_pixels is not None:
            out.update(visible_pixels=self.visible_pixels, points_in_box=self.points_in_box)
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> RejectedBox:
        """The box of :meth:`to_dict`'s data (a missing key is a ``KeyError``)."""
        return cls(object_index=data["object"], object_id=data["id"], class_name=data["class"],
                   reason=data["reason"], visible_pixels=data.get("visible_pixels"),
                   points_in_box=data.get("points_in_box"))


@dataclasses.dataclass(frozen=True)
class FrameRecord:
    """One frame of the dataset, what ``.frames/<frame>.json`` holds: ``frame`` (its 6-digit id), ``house`` id and
    ``index`` there, the viewpoint ``attempt`` that was accepted and ``views_tried`` (valid viewpoints evaluated),
    ``pose`` (3x4 sensor → world, Matterport z-up metres, 9 decimals; ``None`` for a non-finite value), ``yaw``
    (radians, CCW about +z), ``points`` in the scan, ``rays`` cast, the ``kept`` and ``rejected`` boxes."""

    frame: str
    house: str
    index: int
    attempt: int
    views_tried: int
    pose: tuple[tuple[float | None, ...], ...]
    yaw: float | None
    points: int
    rays: int
    kept: tuple[KeptBox, ...]
    rejected: tuple[RejectedBox, ...]

    def to_dict(self) -> dict[str, Any]:
        """The record as JSON data."""
        return {"frame": self.frame, "house": self.house, "index": self.index, "attempt": self.attempt,
                "views_tried": self.views_tried, "pose": [list(row) for row in self.pose], "yaw": self.yaw,
                "points": self.points, "rays": self.rays, "kept": [k.to_dict() for k in self.kept],
                "rejected": [r.to_dict() for r in self.rejected]}  # fmt: skip

    def to_json(self) -> str:
        """The record's file text without its newline: one line, sorted keys (also the manifest's line for it)."""
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> FrameRecord:
        """The record of :meth:`to_dict`'s data (a missing key is a ``KeyError``, a wrong type a ``TypeError``)."""
        return cls(frame=data["frame"], house=data["house"], index=data["index"], attempt=data["attempt"],
                   views_tried=data["views_tried"], pose=tuple(tuple(row) for row in data["pose"]), yaw=data["yaw"],
                   points=data["points"], rays=data["rays"], kept=tuple(KeptBox.from_dict(k) for k in data["kept"]),
                   rejected=tuple(RejectedBox.from_dict(r) for r in data["rejected"]))  # fmt: skip


@dataclasses.dataclass(frozen=True)
class ManifestHouse:
    """One house of the manifest: ``files_sha256`` (file name → hex sha256 of each house file read),
    ``objects_of_class`` (objects of the labelled classes in the house) and ``frames`` (its first and last global
    frame id)."""

    files_sha256: dict[str, str]
    objects_of_class: int
    frames: tuple[int, int]

    def to_dict(self) -> dict[str, Any]:
        """The entry as JSON data."""
        return {"files_sha256": self.files_sha256, "objects_of_class": self.objects_of_class,
                "frames": list(self.frames)}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ManifestHouse:
        """The entry of :meth:`to_dict`'s data."""
        first, last = data["frames"]
        return cls(files_sha256=dict(data["files_sha256"]), objects_of_class=data["objects_of_class"],
                   frames=(first, last))


@dataclasses.dataclass(frozen=True)
class ManifestTotals:
    """Counts over the whole dataset: ``frames``, ``boxes_kept``, ``boxes_rejected`` (reason → count, sorted by
    reason) and scan ``points``."""

    frames: int
    boxes_kept: int
    boxes_rejected: dict[str, int]
    points: int

    def to_dict(self) -> dict[str, Any]:
        """The totals as JSON data."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ManifestTotals:
        """The totals of :meth:`to_dict`'s data."""
        return cls(frames=data["frames"], boxes_kept=data["boxes_kept"],
                   boxes_rejected=dict(data["boxes_rejected"]), points=data["points"])


@dataclasses.dataclass(frozen=True)
class Manifest:
    """What ``manifest.json`` holds: ``format`` (:data:`MANIFEST_FORMAT`), the ``command`` that makes the dataset
    (``--root`` by folder name only), ``config`` (the run's settings, as ``.generate.json`` holds them), package
    ``versions``, ``seed``, ``houses`` (id → :class:`ManifestHouse`, in ``--house`` order), ``conventions`` (what the
    files mean, :func:`conventions`), ``splits`` (name → frames, in train / val / test order), ``totals``, one
    :class:`FrameRecord` per frame in id order and, for a house-disjoint split (``--split-mode house``),
    ``split_houses`` (split name → its house ids, in ``--house`` order; None and absent from the file otherwise)."""

    format: str
    command: tuple[str, ...]
    config: dict[str, Any]
    versions: dict[str, str]
    seed: int
    houses: dict[str, ManifestHouse]
    conventions: dict[str, str]
    splits: dict[str, int]
    totals: ManifestTotals
    frames: tuple[FrameRecord, ...]
    split_houses: dict[str, list[str]] | None = None

    def to_dict(self) -> dict[str, Any]:
        """The manifest as JSON data."""
        return {**self._head(), "frames": [f.to_dict() for f in self.frames]}

    def _head(self) -> dict[str, Any]:
        return {"format": self.format, "command": list(self.command), "config": self.config,
                "versions": self.versions, "seed": self.seed,
                "houses": {hid: h.to_dict() for hid, h in self.houses.items()}, "conventions": self.conventions,
                "splits": self.splits, "totals": self.totals.to_dict(),
                **({"split_houses": self.split_houses} if self.split_houses is not None else {})}  # fmt: skip

    def to_json(self) -> str:
        """The file's text without its final newline: sorted keys, indented by one space, except that the ``frames``
        list holds one compact record per line (:meth:`FrameRecord.to_json`, as in ``.frames/``).

        The records are spliced in as text because json's indenting encoder is pure Python (~0.5 ms per frame, run
        serially after the last frame); the compact one is C. The file parses to the same data either way.
        """
        slot = json.dumps(_FRAMES_SLOT)
        text = json.dumps({**self._head(), "frames": _FRAMES_SLOT}, sort_keys=True, indent=1)
        if text.count(slot) != 1:  # the placeholder also occurs in a user-given value: encode the slow way
            return json.dumps(self.to_dict(), sort_keys=True, indent=1)
        lines = [f.to_json() for f in self.frames]
        return text.replace(slot, "[\n  " + ",\n  ".join(lines) + "\n ]" if lines else "[]")

    def _viewpoint_setting(self, name: str) -> float | None:
        viewpoints = self.config.get("viewpoints")
        value = viewpoints.get(name) if isinstance(viewpoints, dict) else None
        return None if value is None else float(value)

    @property
    def sensor_height(self) -> float | None:
        """The sensor's height above the floor (metres; ``mpchair generate --height``), from the run's settings
        (``config.viewpoints.height``); None in a manifest whose settings lack it."""
        return self._viewpoint_setting("height")

    @property
    def robot_radius(self) -> float | None:
        """The robot's radius (metres; ``mpchair generate --robot-radius``), from the run's settings
        (``config.viewpoints.robot_radius``); None in a manifest whose settings lack it."""
        return self._viewpoint_setting("robot_radius")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], frames: bool = True) -> Manifest:
        """The manifest of :meth:`to_dict`'s data (a missing key is a ``KeyError``, a wrong type a ``TypeError``);
        ``frames=False``: without its per-frame list (``frames`` empty; the list may be absent, as in the run record
        of ``reproduction.record``)."""
        if not isinstance(data["config"], dict):
            raise TypeError("config: expected an object")
        records = data["frames"] if frames else ()
        return cls(format=data["format"], command=tuple(data["command"]), config=data["config"],
                   versions=dict(data["versions"]), seed=data["seed"],
                   houses={hid: ManifestHouse.from_dict(h) for hid, h in data["houses"].items()},
                   conventions=dict(data["conventions"]), splits=dict(data["splits"]),
                   totals=ManifestTotals.from_dict(data["totals"]),
                   split_houses=_split_houses(data.get("split_houses")),
                   frames=tuple(_frame_at(records, i) for i in range(len(records))))  # fmt: skip


#: Placeholder of the manifest's frame list while the rest is encoded (see :meth:`Manifest.to_json`).
_FRAMES_SLOT = "@@frame records@@"


def _frame_at(frames: Sequence[Any], i: int) -> FrameRecord:
    """``frames[i]`` as a record; a bad one names its position."""
    try:
        return FrameRecord.from_dict(frames[i])
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise ValueError(f"frames[{i}]: {_why(e)}") from None


def _split_houses(value: Any) -> dict[str, list[str]] | None:
    """The manifest's optional ``split_houses`` (split → house ids), checked."""
    if value is None:
        return None
    if not isinstance(value, dict) or not all(isinstance(v, list) and all(isinstance(h, str) for h in v)
                                              for v in value.values()):
        raise TypeError("split_houses: expected an object of split name -> list of house ids")
    return {str(k): list(v) for k, v in value.items()}


def _why(e: Exception) -> str:
    return f"missing key {e}" if isinstance(e, KeyError) else str(e)


def conventions(occlusion_cutoffs: Sequence[float]) -> dict[str, str]:
    """The manifest's ``conventions``: what the files of the dataset mean (frames, units, encodings);
    ``occlusion_cutoffs`` the sensor filters' two visible-fraction cutoffs of the KITTI ``occluded`` levels."""
    return {
        "frame": "sensor: x forward, y left, z up, metres (right-handed; the original was mirrored)",
        "velodyne": "float32 x, y, z, 1.0 (constant 4th channel: the sensor has no intensity)",
        "pose": "3x4 row-major sensor -> world (Matterport z-up metres)",
        "bbox_2d": "projection of the 3D box through P2, clipped to the image; truncation = fraction outside",
        "occluded": "0 if visible fraction >= {:.2f}, 1 if >= {:.2f}, else 2 (dense grid)".format(*occlusion_cutoffs),
        "image_2": "8-bit scan depth: 0 none, else 1 + round(254 * (1 - depth / max_range))",
        "misses": "rays without a hit (or outside the range limits) are dropped",
    }


@dataclasses.dataclass(frozen=True)
class RecordCounts:
    """Counts over frame records: boxes ``kept`` (and ``kept_by_class``, mpcat40 name → count, sorted), ``rejected``
    (reason → count, sorted), ``points`` (mean per frame; 0.0 for no record) and ``rays`` (sum)."""

    kept: int
    kept_by_class: dict[str, int]
    rejected: dict[str, int]
    points: float
    rays: int


def describe_records(records: Sequence[FrameRecord]) -> RecordCounts:
    """The :class:`RecordCounts` of ``records`` (``.frames/*.json``, or the manifest's ``frames``)."""
    return RecordCounts(
        kept=sum(len(r.kept) for r in records),
        kept_by_class=dict(sorted(Counter(k.class_name for r in records for k in r.kept).items())),
        rejected=dict(sorted(Counter(k.reason for r in records for k in r.rejected).items())),
        points=float(np.mean([r.points for r in records])) if records else 0.0,
        rays=int(sum(r.rays for r in records)),
    )


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"invalid JSON: {e}", path, getattr(e, "lineno", None)) from None


def read_frame_record(path: str | Path) -> FrameRecord:
    """The :class:`FrameRecord` in ``path`` (``DIR/.frames/NNNNNN.json``); one that does not hold a frame record is
    an :class:`InputError` naming the file."""
    data = _read_json(Path(path))
    try:
        if not isinstance(data, dict):
            raise TypeError("expected a JSON object")
        return FrameRecord.from_dict(data)
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise InputError(f"not an mpchair frame record: {_why(e)}", path) from None


def read_manifest(root: str | Path, frames: bool = True) -> Manifest | None:
    """The :class:`Manifest` of the dataset folder ``root`` (``<root>/manifest.json``), or ``None`` when the folder
    has none (real KITTI). A file that is not valid JSON, or not an mpchair manifest (a key missing, a wrong type), is
    an :class:`InputError` naming it (and the line, or the frame). ``frames=False``: the manifest without its
    per-frame list (not parsed, and not required: a run record's copy leaves it out)."""
    path = Path(root) / MANIFEST_NAME
    if not path.is_file():
        return None
    data = _read_json(path)
    if not isinstance(data, dict):
        raise InputError("expected a JSON object", path)
    try:
        return Manifest.from_dict(data, frames=frames)
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise InputError(f"not an mpchair manifest: {_why(e)}", path) from None
