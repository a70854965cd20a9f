"""Dataset statistics: pseudoimage density ``D`` per frame and box statistics, on any KITTI-layout folder.

Both work on an mpchair dataset (``mpchair generate``) and on a real KITTI folder: frames are the
``<root>/training/velodyne/*.bin`` scans (or the ids of ``<root>/ImageSets/<split>.txt``), with ``label_2``,
``calib`` and ``image_2`` beside them.

**Density** (Sparse PointPillars paper, section IV): ``D = non-empty pillars / (W * H)`` of the model's pseudoimage.
Pillars are indexed with :func:`mpchair.geometry.pillar_coords`, the very function the detector's voxelizer calls:
a point is kept iff ``min <= p < max`` on x, y and z of ``point_cloud_range`` (sensor frame, metres) and its pillar
is ``floor((p - min) / voxel)``. ``W x H`` is the model's ``output_shape`` (``[ny, nx]`` in the YAML), i.e. the
*padded* canvas the backbone convolves, which may be larger than the range's real grid (Matterport-Chair: real
500 x 760 in a 512 x 768 canvas; KITTI: real 432 x 496 in 440 x 504).

**Boxes**: non-DontCare rows of ``label_2`` are turned into sensor-frame boxes with the frame's calib
(:func:`mpchair.geometry.labels_to_boxes`); per class we report count, ``l, w, h`` mean/std (the anchor a config
should use), points inside each box (the scan's points, faces inclusive), centre distance ``hypot(x, y)`` and yaw
(heading, CCW about +z, ``[-pi, pi)``) distributions, the label file's occlusion and truncation levels, and the
manifest's rejected-box reasons when the dataset has a ``manifest.json``.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mpchair.core.errors import InputError
from mpchair.dataset.manifest import read_manifest
from mpchair.geometry import fov_mask, labels_to_boxes, points_in_boxes
from mpchair.geometry.pillars import (  # noqa: F401  (re-exported: stats --density works on these)
    KITTI_GEOMETRY,
    MATTERPORT_GEOMETRY,
    PRESETS,
    PseudoimageGeometry,
    frame_density,
    geometry_from_model_yaml,
)
from mpchair.kitti import (
    frame_paths,
    imageset_path,
    read_calib,
    read_image_size,
    read_imageset,
    read_labels,
    read_velodyne,
)
from mpchair.paper import KITTI_DENSITY, MATTERPORT_CHAIR_DENSITY

#: The paper's reported densities (``mpchair.paper``, section IV; "test data"): median, min, max.
PAPER_DENSITY: dict[str, dict[str, float]] = {
    "matterport_chair": MATTERPORT_CHAIR_DENSITY.to_json(),
    "kitti": KITTI_DENSITY.to_json(),
}

#: Percentiles reported by :func:`summarize` (besides min / median / max).
PERCENTILES: tuple[int, ...] = (5, 10, 25, 75, 90, 95)


# ----------------------------------------------------------------------------------------------------------- frames


def dataset_frame_ids(root: str | Path, split: str | None = None) -> list[str]:
    """Frame ids of a KITTI-layout dataset: ``ImageSets/<split>.txt`` when ``split`` is given, else every
    ``training/velodyne/*.bin`` (sorted). No frames is an :class:`InputError`.
    """
    root = Path(root)
    if not root.is_dir():
        raise InputError("dataset folder not found", root)
    if split is not None:
        ids = read_imageset(imageset_path(root, split))
        where = imageset_path(root, split)
    else:
        velo = root / "training" / "velodyne"
        if not velo.is_dir():
            raise InputError("no training/velodyne folder (not a KITTI-layout dataset)", root)
        ids = sorted(p.stem for p in velo.glob("*.bin"))
        where = velo
    if not ids:
        raise InputError("no frames", where)
    return ids


def load_points(root: str | Path, frame_id: str, fov_crop: bool = False, split_dir: str = "training") -> np.ndarray:
    """The (N,4) float32 scan of a frame (sensor frame, metres), optionally cropped to the image_2 field of view
    (``split_dir``: the folder under ``root`` holding ``velodyne/``; ``""`` for a stream's sequence folder).

    The crop (:func:`mpchair.geometry.fov_mask`) uses the frame's calib and its real image size, read from
    ``image_2/<id>.png`` (sizes differ per frame on KITTI), like OpenPCDet's ``FOV_POINTS_ONLY``.
    """
    paths = frame_paths(root, frame_id, split_dir)
    points = read_velodyne(paths.velodyne)
    if fov_crop:
        calib = read_calib(paths.calib)
        points = points[fov_mask(points, calib, read_image_size(paths.image_2))]
    return points


# ---------------------------------------------------------------------------------------------------------- density


def summarize(values: Sequence[float]) -> dict:
    """``count, min, median, mean, std, max`` and ``percentiles`` (``{"5": ..}``, linear interpolation)."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        return {"count": 0}
    return {
        "count": int(v.size),
        "min": float(v.min()),
        "median": float(np.median(v)),
        "mean": float(v.mean()),
        "std": float(v.std()),
        "max": float(v.max()),
        "percentiles": {str(p): float(np.percentile(v, p)) for p in PERCENTILES},
    }


def density_stats(
    root: str | Path,
    geometry: PseudoimageGeometry = MATTERPORT_GEOMETRY,
    split: str | None = None,
    fov_crop: bool = False,
) -> dict:
    """Pseudoimage density of every frame of a dataset (see the module docstring).

    Returns a JSON-able dict: ``dataset``, ``split``, ``fov_crop``, ``geometry``, the :func:`summarize` keys over the
    per-frame ``D``, ``paper`` (:data:`PAPER_DENSITY`) and ``frames``: ``[{id, points, points_in_range, pillars,
    density}]`` in frame order.
    """
    frames = []
    for fid in dataset_frame_ids(root, split):
        points = load_points(root, fid, fov_crop)
        in_range, pillars, d = frame_density(points, geometry)
        frames.append({"id": fid, "points": int(len(points)), "points_in_range": in_range, "pillars": pillars,
                       "density": d})
    return {
        "dataset": str(root),
        "split": split,
        "fov_crop": fov_crop,
        "geometry": geometry.to_dict(),
        **summarize([f["density"] for f in frames]),
        "paper": PAPER_DENSITY,
        "frames": frames,
    }


def format_density(stats: dict) -> str:
    """Human-readable summary of :func:`density_stats` (no per-frame values)."""
    g = stats["geometry"]
    p = stats["percentiles"]
    lines = [
        f"dataset {stats['dataset']}  split {stats['split'] or 'all'}  fov_crop {stats['fov_crop']}",
        f"grid {g['grid'][0]} x {g['grid'][1]} (real {g['real_grid'][0]} x {g['real_grid'][1]})  voxel "
        f"{g['voxel_size'][0]:g} x {g['voxel_size'][1]:g} m  range {g['point_cloud_range']}",
        f"frames {stats['count']}",
        f"density D  min {stats['min']:.5f}  median {stats['median']:.5f}  mean {stats['mean']:.5f}  "
        f"max {stats['max']:.5f}  std {stats['std']:.5f}",
        "percentiles  " + "  ".join(f"p{k} {v:.5f}" for k, v in p.items()),
        "paper medians  Matterport-Chair {:.5f}  KITTI {:.5f}".format(
            stats["paper"]["matterport_chair"]["median"], stats["paper"]["kitti"]["median"]),
    ]
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------------------ boxes

#: Bin edges of the box histograms (distance in metres, yaw in radians, truncation fraction).
YAW_BINS = 12
TRUNCATION_EDGES: tuple[float, ...] = (0.0, 0.1, 0.3, 0.5, 0.7, 1.0)


def read_manifest_rejections(root: str | Path) -> dict | None:
    """Rejected-box reasons of ``<root>/manifest.json`` as ``{reason: count}`` (sorted by count, descending), or
    ``None`` when the dataset has no manifest (real KITTI).

    The manifest holds per-frame kept and rejected boxes (:class:`mpchair.dataset.manifest.FrameRecord`); every
    rejected box carries the ``reason`` (the first filter it failed). A manifest that is not valid JSON, or not an
    mpchair manifest, is an :class:`InputError` (:func:`mpchair.dataset.manifest.read_manifest`).
    """
    manifest = read_manifest(root)
    if manifest is None:
        return None
    counts = Counter(box.reason for frame in manifest.frames for box in frame.rejected)
    return dict(sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


def box_records(root: str | Path, frame_ids: Sequence[str], classes: Sequence[str] | None = None) -> tuple[dict, list]:
    """Per-box records of the given frames: ``({class: {field: array}}, boxes_per_frame)``.

    Fields: ``l, w, h`` (metres), ``points`` (scan points inside the box, faces inclusive), ``distance``
    (``hypot(x, y)`` of the centre, sensor frame, metres), ``yaw`` (radians ``[-pi, pi)``), ``occluded`` (label
    value), ``truncated`` (label value). ``boxes_per_frame`` counts the selected boxes of every frame (0 included).
    DontCare rows are skipped; ``classes`` keeps only those label names (compared case-insensitively).
    """
    recs: dict[str, dict[str, list]] = {}
    per_frame = []
    for fid in frame_ids:
        paths = frame_paths(root, fid)
        labels = read_labels(paths.label_2).objects()
        if classes:  # case-insensitive, as detector eval's --classes
            labels = labels[np.isin(np.char.lower(labels.names.astype(str)), [c.lower() for c in classes])]
        per_frame.append(len(labels))
        if len(labels) == 0:
            continue
        boxes = labels_to_boxes(labels, read_calib(paths.calib))
        counts = points_in_boxes(read_velodyne(paths.velodyne)[:, :3], boxes).sum(axis=1)
        for k in range(len(labels)):
            r = recs.setdefault(str(labels.names[k]), {key: [] for key in
                                                      ("l", "w", "h", "points", "distance", "yaw", "occluded",
                                                       "truncated")})
            r["l"].append(boxes[k, 3])
            r["w"].append(boxes[k, 4])
            r["h"].append(boxes[k, 5])
            r["points"].append(int(counts[k]))
            r["distance"].append(math.hypot(boxes[k, 0], boxes[k, 1]))
            r["yaw"].append(boxes[k, 6])
            r["occluded"].append(int(labels.occluded[k]))
            r["truncated"].append(float(labels.truncated[k]))
    out = {name: {k: np.asarray(v) for k, v in fields.items()} for name, fields in sorted(recs.items())}
    return out, per_frame


def _histogram(values: np.ndarray, edges: np.ndarray) -> dict:
    counts, edges = np.histogram(values, bins=edges)
    return {"edges": [float(e) for e in edges], "counts": [int(c) for c in counts]}


def box_stats(root: str | Path, split: str | None = None, classes: Sequence[str] | None = None) -> dict:
    """Box statistics of a dataset (see the module docstring) as a JSON-able dict.

    Keys: ``dataset``, ``split``, ``frames`` (count), ``boxes_per_frame`` (:func:`summarize` + ``histogram`` of
    counts 0..max), ``classes``: per class ``count``, ``l/w/h`` (``mean``, ``std``, ``min``, ``max``, ``histogram``;
    metres), ``anchor_lwh`` (the means), ``points`` / ``distance`` (:func:`summarize` + ``histogram``), ``yaw``
    (``histogram`` over ``[-pi, pi)`` in :data:`YAW_BINS` bins), ``occluded`` (``{level: count}``), ``truncated``
    (:func:`summarize` + ``histogram`` over :data:`TRUNCATION_EDGES`); ``rejected`` (manifest reasons or ``None``);
    and ``per_frame`` (``[{id, boxes}]``).
    """
    ids = dataset_frame_ids(root, split)
    recs, per_frame = box_records(root, ids, classes)
    classes_out = {}
    for name, r in recs.items():
        dims = {}
        for key in ("l", "w", "h"):
            v = r[key]
            lo, hi = float(v.min()), float(v.max())
            dims[key] = {"mean": float(v.mean()), "std": float(v.std()), "min": lo, "max": hi,
                         "histogram": _histogram(v, np.linspace(lo - 0.05, hi + 0.05, 16))}
        dmax = max(1.0, math.ceil(float(r["distance"].max())))
        pmax = max(1, int(r["points"].max()))
        classes_out[name] = {
            "count": int(len(r["l"])),
            **dims,
            "anchor_lwh": [dims["l"]["mean"], dims["w"]["mean"], dims["h"]["mean"]],
            "points": {**summarize(r["points"]),
                       "histogram": _histogram(r["points"], np.unique(np.geomspace(1, pmax + 1, 13).round()) - 1)},
            "distance": {**summarize(r["distance"]), "histogram": _histogram(r["distance"], np.linspace(0, dmax, 11))},
            "yaw": {**summarize(r["yaw"]),
                    "histogram": _histogram(r["yaw"], np.linspace(-math.pi, math.pi, YAW_BINS + 1))},
            "occluded": {str(k): int(c) for k, c in sorted(Counter(r["occluded"].tolist()).items())},
            "truncated": {**summarize(r["truncated"]),
                          "histogram": _histogram(r["truncated"], np.asarray(TRUNCATION_EDGES))},
        }
    bpf = np.asarray(per_frame)
    return {
        "dataset": str(root),
        "split": split,
        "frames": len(ids),
        "boxes_per_frame": {**summarize(bpf),
                            "histogram": {str(k): int(c) for k, c in enumerate(np.bincount(bpf))}},
        "classes": classes_out,
        "rejected": read_manifest_rejections(root),
        "per_frame": [{"id": fid, "boxes": int(n)} for fid, n in zip(ids, per_frame)],
    }


def format_boxes(stats: dict) -> str:
    """Human-readable summary of :func:`box_stats`."""
    b = stats["boxes_per_frame"]
    lines = [
        f"dataset {stats['dataset']}  split {stats['split'] or 'all'}  frames {stats['frames']}",
        f"boxes per frame  min {b['min']:g}  median {b['median']:g}  mean {b['mean']:.2f}  max {b['max']:g}",
    ]
    for name, c in stats["classes"].items():
        lines.append(f"{name}: {c['count']} boxes")
        lines.append("  l {:.3f} ± {:.3f}  w {:.3f} ± {:.3f}  h {:.3f} ± {:.3f} m   anchor [l, w, h] = [{}]".format(
            c["l"]["mean"], c["l"]["std"], c["w"]["mean"], c["w"]["std"], c["h"]["mean"], c["h"]["std"],
            ", ".join(f"{v:.3f}" for v in c["anchor_lwh"])))
        p, d = c["points"], c["distance"]
        lines.append(f"  points/box  min {p['min']:g}  median {p['median']:g}  mean {p['mean']:.1f}  max {p['max']:g}")
        lines.append(f"  distance    min {d['min']:.2f}  median {d['median']:.2f}  max {d['max']:.2f} m")
        lines.append("  occluded    " + "  ".join(f"{k}: {v}" for k, v in c["occluded"].items()))
        t = c["truncated"]
        lines.append(f"  truncated   mean {t['mean']:.3f}  max {t['max']:.3f}")
    if stats["rejected"] is not None:
        total = sum(stats["rejected"].values())
        lines.append(f"rejected boxes (manifest): {total}")
        lines.extend(f"  {reason}: {n}" for reason, n in stats["rejected"].items())
    return "\n".join(lines)
