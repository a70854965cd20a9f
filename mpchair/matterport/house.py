"""The :class:`House`: one Matterport3D house (mesh, per-face labels, objects with boxes, regions, levels).

:func:`read_house` joins the ``.house`` records with the labelled mesh of either layout (``mpchair.matterport.source``):

- **release** ``<id>.ply``: along the chain habitat's converter used, ``face.material_id`` → the ``E`` record with that
  ``id`` → ``E.object`` → ``O`` → ``C[O.category]`` → mpcat40 index. The ``.ply``'s own ``segment_id`` (object index)
  and ``category_id`` (category_mapping index) are cross-checked and the disagreeing fraction of faces is reported as
  ``label_mismatch_rate``;
- **habitat** ``<id>_semantic.ply``: each face's ``object_id`` is that ``O`` record's index already (-1, or any id
  outside ``[0, #O)``, is unlabelled); no E lookup, no second label to cross-check (``label_mismatch_rate`` None).

The same house read from either layout gives the same vertices, faces, objects and per-face labels. A ``<id>.navmesh``
beside the files is read too (``House.navmesh``). Everything is in the raw Matterport world frame (metres, z up).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mpchair.core.errors import InputError
from mpchair.geometry import habitat_to_mp3d
from mpchair.matterport.boxes import TILT_WARN_DEG, aligned_box, orthonormal_axes
from mpchair.matterport.categories import mpcat40_name, resolve_categories
from mpchair.matterport.housefile import (
    CategoryRecord,
    HouseFile,
    ImageRecord,
    PanoramaRecord,
    PortalRecord,
    parse_house_text,
    region_height,
)
from mpchair.matterport.jsonfiles import SegGroup, read_fsegs, read_semseg
from mpchair.matterport.navmesh import NavMesh, read_navmesh
from mpchair.matterport.ply import PlyMesh, read_ply, read_semantic_ply
from mpchair.matterport.source import HouseSource, find_houses

#: Frame check of a semantic mesh: this fraction of its vertices must lie inside the ``.house`` ``H`` box grown by
#: ``FRAME_BOX_MARGIN`` metres (real scans reach a little beyond the annotated box; a mesh in another frame does not).
FRAME_INSIDE_MIN = 0.99
FRAME_BOX_MARGIN = 0.5

#: Region labels (one character, data_organization.md) → names.
REGION_LABELS = {
    "a": "bathroom", "b": "bedroom", "c": "closet", "d": "dining room", "e": "entryway", "f": "family room",
    "g": "garage", "h": "hallway", "i": "library", "j": "laundry/mudroom", "k": "kitchen", "l": "living room",
    "m": "meeting room", "n": "lounge", "o": "office", "p": "porch/terrace", "r": "rec/game", "s": "stairs",
    "t": "toilet", "u": "utility", "v": "tv", "w": "gym", "x": "outdoor", "y": "balcony", "z": "other room",
    "B": "bar", "C": "classroom", "D": "dining booth", "S": "spa/sauna", "Z": "junk", "-": "no label",
}  # fmt: skip


class HouseWarning(UserWarning):
    """A recoverable oddity in a house (tilted object box, label mismatches, side file disagreeing with the mesh)."""


@dataclass(frozen=True, eq=False)
class HouseObject:
    """One annotated object (an ``O`` record) with its category and boxes (world frame, metres).

    ``index`` is the O index (what faces carry as ``segment_id``); ``id`` is habitat's ``"<level>_<region>_<index>"``;
    ``region`` the R index (-1 none); ``raw_category`` the category_mapping name (spaces, not ``#``; ``""`` none);
    ``category_index`` the C index (-1 none); ``mapping_index`` the category_mapping index (-1 none);
    ``mpcat40_index``/``mpcat40_name`` (-1/``"none"`` when uncategorised). OBB: ``center (3,)``, ``axes (3,3)`` rows
    a0, a1, a2 (orthonormal, a2 = a0 × a1), ``radii (3,)`` half-lengths. ``aligned_box (7,)`` [x, y, z_center, l, w,
    h, yaw] is the vertically aligned yaw-only box; ``tilt_deg`` the up axis's angle to world z.
    """

    index: int
    id: str
    region: int
    raw_category: str
    category_index: int
    mapping_index: int
    mpcat40_index: int
    mpcat40_name: str
    center: np.ndarray
    axes: np.ndarray
    radii: np.ndarray
    aligned_box: np.ndarray
    tilt_deg: float


@dataclass(frozen=True, eq=False)
class Region:
    """One region (room): ``index``, ``level`` (-1 none), ``label`` code and ``label_name``; ``floor_polygon (K,2)``
    world xy of its floor surface (``S`` label ``F`` with its ``V`` records, CCW; (0,2) when absent); ``floor_z`` (the
    floor polygon's mean z, else the AABB bottom), ``height`` (file value or GAPS fallback), ``position (3,)``,
    ``bbox (6,)`` [xlo ylo zlo xhi yhi zhi] (world metres)."""

    index: int
    level: int
    label: str
    label_name: str
    floor_polygon: np.ndarray
    floor_z: float
    height: float
    position: np.ndarray
    bbox: np.ndarray


@dataclass(frozen=True, eq=False)
class Level:
    """One level: ``index``, ``label``, ``regions`` (R indices on it), ``position (3,)``, ``bbox (6,)`` (world)."""

    index: int
    label: str
    regions: tuple[int, ...]
    position: np.ndarray
    bbox: np.ndarray


@dataclass(frozen=True, eq=False)
class House:
    """One house (see module docstring). Arrays are in the Matterport world frame (metres, z up).

    ``vertices (V,3) float64``, ``faces (F,3) int64`` (file order), ``face_object (F,) int64`` (position in
    ``objects``, -1 unlabelled), ``face_category (F,) int64`` (mpcat40 index, -1 none), ``face_segment (F,)`` the raw
    per-face label (release: ``material_id``; habitat: ``object_id``). ``label_mismatch_rate`` is the fraction of faces
    whose ``segment_id``/``category_id`` disagree with the material chain (None for the habitat layout, which has no
    second label). ``warnings`` collects recoverable oddities (also issued as :class:`HouseWarning`). ``layout`` is
    ``"release"`` or ``"habitat"``; ``navmesh`` the house's habitat navmesh (world frame) when it has one.
    """

    id: str
    version: str
    vertices: np.ndarray
    faces: np.ndarray
    face_object: np.ndarray
    face_category: np.ndarray
    face_segment: np.ndarray
    objects: tuple[HouseObject, ...]
    regions: tuple[Region, ...]
    levels: tuple[Level, ...]
    categories: tuple[CategoryRecord, ...]
    portals: tuple[PortalRecord, ...]
    panoramas: tuple[PanoramaRecord, ...]
    images: tuple[ImageRecord, ...]
    seg_groups: tuple[SegGroup, ...]
    bbox: np.ndarray
    label_mismatch_rate: float | None
    warnings: tuple[str, ...]
    layout: str = "release"
    navmesh: NavMesh | None = None

    @property
    def unlabelled_faces(self) -> int:
        """Number of faces that belong to no object."""
        return int(np.count_nonzero(self.face_object < 0))

    def objects_by_category(self) -> dict[str, int]:
        """Object counts per mpcat40 name (``"none"`` for uncategorised objects), sorted by name."""
        counts: dict[str, int] = {}
        for o in self.objects:
            counts[o.mpcat40_name] = counts.get(o.mpcat40_name, 0) + 1
        return dict(sorted(counts.items()))


def objects_of(house: House, categories: Iterable[str | int] | str | int) -> tuple[HouseObject, ...]:
    """The objects of ``house`` whose mpcat40 class is one of ``categories`` (names like ``"chair"`` or indices)."""
    wanted = resolve_categories(categories)
    return tuple(o for o in house.objects if o.mpcat40_index in wanted)


def _build_objects(hf: HouseFile, region_level: dict[int, int], path: str) -> tuple[list[HouseObject], list[str]]:
    out, notes = [], []
    for o in hf.objects:
        axes = orthonormal_axes(o.axis0, o.axis1)
        box, tilt = aligned_box(o.center, axes, o.radii)
        if tilt > TILT_WARN_DEG:
            notes.append(f"{path}: object {o.index} box is tilted {tilt:.1f} deg from vertical")
        if o.category >= 0:
            c = hf.categories[o.category]
            raw, mapping, mp = c.mapping_name, c.mapping_index, c.mpcat40_index
            # Trust the index; the name in the file is informative only (it may use '#' or differ in case).
            name = mpcat40_name(mp) if 0 <= mp <= 41 else (c.mpcat40_name or "none")
        else:
            raw, mapping, mp, name = "", -1, -1, "none"
        out.append(
            HouseObject(
                index=o.index, id=f"{region_level.get(o.region, -1)}_{o.region}_{o.index}", region=o.region,
                raw_category=raw, category_index=o.category, mapping_index=mapping, mpcat40_index=mp,
                mpcat40_name=name, center=o.center.copy(), axes=axes, radii=o.radii.copy(), aligned_box=box,
                tilt_deg=tilt,
            )  # fmt: skip
        )
    return out, notes


def _build_regions(hf: HouseFile) -> list[Region]:
    # Floor polygons: V records grouped by surface, surfaces labelled F grouped by region.
    verts_by_surface: dict[int, list] = {}
    for v in hf.vertices:
        verts_by_surface.setdefault(v.surface, []).append(v.position)
    floor_by_region: dict[int, np.ndarray] = {}
    for s in hf.surfaces:
        if s.label.upper() == "F" and s.index in verts_by_surface and s.region not in floor_by_region:
            floor_by_region[s.region] = np.asarray(verts_by_surface[s.index], dtype=np.float64)
    regions = []
    for r in hf.regions:
        poly3 = floor_by_region.get(r.index)
        if poly3 is not None and len(poly3):
            poly = poly3[:, :2].copy()
            floor_z = float(poly3[:, 2].mean())
        else:
            poly = np.zeros((0, 2))
            floor_z = float(r.bbox[2])
        regions.append(
            Region(
                index=r.index, level=r.level, label=r.label, label_name=REGION_LABELS.get(r.label, "unknown"),
                floor_polygon=poly, floor_z=floor_z, height=region_height(r), position=r.position.copy(),
                bbox=r.bbox.copy(),
            )  # fmt: skip
        )
    return regions


def _segment_lookup(material: np.ndarray, seg_ids: np.ndarray, seg_values: np.ndarray) -> np.ndarray:
    """For every face's ``material_id``, the value of the E record with that id (-1 where none matches)."""
    if len(seg_ids) == 0:
        return np.full(len(material), -1, dtype=np.int64)
    order = np.argsort(seg_ids, kind="stable")
    ids_sorted = seg_ids[order]
    pos = np.searchsorted(ids_sorted, material)
    pos_c = np.minimum(pos, len(ids_sorted) - 1)
    hit = ids_sorted[pos_c] == material
    return np.where(hit, seg_values[order][pos_c], -1)


def read_house(source: HouseSource | str | Path, *, side_files: bool = True, navmesh: bool = True) -> House:
    """Read one house from a :class:`HouseSource` (or a path that :func:`find_houses` resolves to exactly one house),
    in either layout (module docstring).

    ``side_files`` also reads ``.fsegs.json`` (cross-checked against ``material_id``) and ``.semseg.json`` (kept as
    ``seg_groups``) when present (release layout); ``navmesh`` reads ``<id>.navmesh`` when present. Recoverable
    oddities go to ``House.warnings`` and are issued as :class:`HouseWarning`; bad input raises :class:`InputError`
    naming the file and line or record.
    """
    if not isinstance(source, HouseSource):
        found = find_houses(source)
        if len(found) != 1:
            raise InputError(f"expected one house, found {len(found)} ({', '.join(found)})", source)
        source = next(iter(found.values()))
    house_path = source.describe(".house")
    raw = source.read_bytes(".house")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    hf = parse_house_text(text, house_path)
    notes: list[str] = []
    region_level = {r.index: r.level for r in hf.regions}
    objects, obj_notes = _build_objects(hf, region_level, house_path)
    notes += obj_notes

    o_index = np.array([o.index for o in hf.objects], dtype=np.int64)
    if source.layout == "habitat":
        mesh, face_object, face_segment, rate, seg_groups = _habitat_faces(source, hf, o_index, notes)
    else:
        mesh, face_object, face_segment, rate, seg_groups = _release_faces(source, hf, objects, o_index, notes,
                                                                           side_files)  # fmt: skip
    obj_mp = np.array([o.mpcat40_index for o in objects] + [-1], dtype=np.int64)
    # Index -1 picks the appended sentinel, so unlabelled faces map to -1 without a branch.
    face_category = obj_mp[face_object]
    if hf.version == "1.0" or not objects:
        notes.append(f"{house_path}: no objects (ASCII {hf.version}); regions and floors only")
    nav = None
    if navmesh and source.exists(".navmesh"):
        nav = read_navmesh(source.read_bytes(".navmesh"), source.describe(".navmesh"))

    levels = []
    for lv in hf.levels:
        regs = tuple(r.index for r in hf.regions if r.level == lv.index)
        levels.append(Level(lv.index, lv.label, regs, lv.position.copy(), lv.bbox.copy()))
    for n in notes:
        warnings.warn(n, HouseWarning, stacklevel=2)
    return House(
        id=source.id, version=hf.version, vertices=mesh.vertices, faces=mesh.faces, face_object=face_object,
        face_category=face_category, face_segment=face_segment, objects=tuple(objects),
        regions=tuple(_build_regions(hf)), levels=tuple(levels), categories=hf.categories, portals=hf.portals,
        panoramas=hf.panoramas, images=hf.images, seg_groups=seg_groups, bbox=hf.header.bbox.copy(),
        label_mismatch_rate=rate, warnings=tuple(notes), layout=source.layout, navmesh=nav,
    )  # fmt: skip


def _release_faces(source: HouseSource, hf: HouseFile, objects: list[HouseObject], o_index: np.ndarray,
                   notes: list[str], side_files: bool) -> tuple:
    """Release ``<id>.ply``: mesh, face → object along the material chain, raw material ids, mismatch rate and the
    ``.semseg.json`` groups (side files cross-checked into ``notes``)."""
    house_path, ply_path = source.describe(".house"), source.describe(".ply")
    mesh = read_ply(source.read_bytes(".ply"), ply_path)
    nf = len(mesh.faces)
    pos_of_index = {int(i): p for p, i in enumerate(o_index)}
    seg_ids = np.array([e.id for e in hf.segments], dtype=np.int64)
    seg_obj = np.array([pos_of_index.get(e.object, -1) for e in hf.segments], dtype=np.int64)
    if len(np.unique(seg_ids)) != len(seg_ids):
        notes.append(f"{house_path}: duplicate E segment ids; faces take the first E record with their id")
        _, first = np.unique(seg_ids, return_index=True)
        seg_ids, seg_obj = seg_ids[first], seg_obj[first]
    if mesh.material_id is None:
        raise InputError("house mesh lacks the per-face 'material_id' property", ply_path)
    face_object = _segment_lookup(mesh.material_id, seg_ids, seg_obj)
    obj_map = np.array([o.mapping_index for o in objects] + [-1], dtype=np.int64)

    mismatch = np.zeros(nf, dtype=bool)
    if mesh.segment_id is not None:
        expect_seg = np.append(o_index, -1)[face_object]
        mismatch |= mesh.segment_id != expect_seg
    if mesh.category_id is not None:
        mismatch |= mesh.category_id != obj_map[face_object]
    # Real houses disagree on a small fraction of faces; that is recorded as a rate, not raised as a warning.
    rate = float(np.count_nonzero(mismatch)) / nf if nf else 0.0

    seg_groups: tuple[SegGroup, ...] = ()
    if side_files:
        if source.exists(".fsegs.json"):
            fsegs = read_fsegs(source.read_bytes(".fsegs.json"), source.describe(".fsegs.json"))
            if len(fsegs) != nf:
                notes.append(f"{source.describe('.fsegs.json')}: {len(fsegs)} segIndices for {nf} faces")
            elif nf and (fsegs != mesh.material_id).any():
                frac = float(np.mean(fsegs != mesh.material_id))
                notes.append(f"{source.describe('.fsegs.json')}: {frac:.2%} of segIndices differ from material_id")
        if source.exists(".semseg.json"):
            seg_groups = read_semseg(source.read_bytes(".semseg.json"), source.describe(".semseg.json"))
    return mesh, face_object, mesh.material_id, rate, seg_groups


def _habitat_faces(source: HouseSource, hf: HouseFile, o_index: np.ndarray, notes: list[str]) -> tuple:
    """habitat ``<id>_semantic.ply``: mesh (frame-checked), face → object from ``object_id``, the raw ids."""
    ply_path = source.describe("_semantic.ply")
    mesh = read_semantic_ply(source.read_bytes("_semantic.ply"), ply_path)
    mesh = _check_frame(mesh, hf.header.bbox, ply_path, notes)
    ids = mesh.object_id
    # O index → position in House.objects (indices are unique; usually equal to the position).
    pos_of = np.full(int(o_index.max()) + 1 if len(o_index) else 0, -1, dtype=np.int64)
    pos_of[o_index] = np.arange(len(o_index))
    known = (ids >= 0) & (ids < len(pos_of))
    face_object = np.full(len(ids), -1, dtype=np.int64)
    face_object[known] = pos_of[ids[known]]
    missing = (ids >= 0) & (ids < len(o_index)) & (face_object < 0)
    if missing.any():
        f = int(np.flatnonzero(missing)[0])
        raise InputError(f"face {f} has object_id {int(ids[f])} but the .house has no O record with that index "
                         f"({int(np.count_nonzero(missing))} faces like it)", ply_path)  # fmt: skip
    stray = (ids != -1) & (face_object < 0)
    if stray.any():
        notes.append(f"{ply_path}: {int(np.count_nonzero(stray))} faces have an object_id outside [0, {len(o_index)}) "
                     "(read as unlabelled)")  # fmt: skip
    return mesh, face_object, ids, None, ()


def _check_frame(mesh: PlyMesh, bbox: np.ndarray, path: str, notes: list[str]) -> PlyMesh:
    """The semantic mesh as stored must be in the ``.house`` frame (z up): at least :data:`FRAME_INSIDE_MIN` of its
    vertices inside the ``H`` box grown by :data:`FRAME_BOX_MARGIN`. A mesh re-exported in habitat's y-up frame is
    converted back (with a warning); anything else is an :class:`InputError`."""
    if len(mesh.vertices) == 0 or not np.any(bbox):
        return mesh
    lo, hi = bbox[:3] - FRAME_BOX_MARGIN, bbox[3:] + FRAME_BOX_MARGIN

    def inside(v: np.ndarray) -> float:
        return float(np.mean(np.all((v >= lo) & (v <= hi), axis=1)))

    frac = inside(mesh.vertices)
    if frac >= FRAME_INSIDE_MIN:
        return mesh
    converted = habitat_to_mp3d(mesh.vertices)
    if inside(converted) >= FRAME_INSIDE_MIN:
        notes.append(f"{path}: vertices are in habitat's y-up frame (re-exported?); converted (x, y, z) -> (x, -z, y)")
        return dataclasses.replace(mesh, vertices=converted)
    raise InputError(f"only {frac:.1%} of the vertices lie inside the .house H box grown by {FRAME_BOX_MARGIN} m "
                     f"(need {FRAME_INSIDE_MIN:.0%}; also in habitat's y-up frame): not this house's mesh, or not in "
                     "its frame", path)  # fmt: skip


def habitat_object_ids(hf: HouseFile, material_id: np.ndarray) -> np.ndarray:
    """(F,) int64 the ``object_id`` habitat's converter (``Mp3dInstanceMeshData``) wrote per face of the release mesh:
    ``material_id`` → the E record with that id → its O index (-1 when no E record matches or it has no object)."""
    seg_ids = np.array([e.id for e in hf.segments], dtype=np.int64)
    seg_obj = np.array([e.object for e in hf.segments], dtype=np.int64)
    return _segment_lookup(np.asarray(material_id, dtype=np.int64), seg_ids, seg_obj)


def aligned_boxes(objects: Iterable[HouseObject]) -> np.ndarray:
    """Stack the objects' aligned boxes into an (N,7) float64 array (world frame); (0,7) for none."""
    boxes = [o.aligned_box for o in objects]
    return np.stack(boxes) if boxes else np.zeros((0, 7))


__all__ = [
    "House", "HouseObject", "HouseWarning", "Level", "Region", "aligned_boxes", "habitat_object_ids", "objects_of",
    "read_house",
]  # fmt: skip
