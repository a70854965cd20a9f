"""Procedural homes in the Matterport3D release format, and the construction record tests compare the reader with.

Recipe (all lengths in metres): a grid of 2-3 x 2 rooms (each at least 3.4 m across) per level, walls 0.12 m thick
built from closed boxes with door openings between rooms, an entry door and windows in the outer walls, floor and
ceiling slabs, optionally a second level reached by a straight stair through a floor opening with a railing, and an
unreconstructed hole in a top-level ceiling. Rooms are furnished by type (dining, kitchen, living, office, bedroom,
bath, hallway): tables with chairs around them (some pushed under), sofas, cabinets, beds, stools, benches and chairs
of five styles against walls or free-standing at random yaw. A few junk fragments are left unlabelled. The house is
then rotated by a random yaw and shifted by a random offset, so nothing is axis-aligned to the world. A
:class:`~mpchair.synth.realism.Realism` other than ``CLEAN`` then adds clutter, door leaves and open-plan openings
(:func:`_add_clutter`, from the realism stream) and, after every object's true box is measured, reconstruction
artifacts (:func:`mpchair.synth.artifacts.apply_artifacts`).

:func:`synthesize_house` returns a :class:`SyntheticHouse`: the records, the mesh with its per-face fields and the
ground-truth objects (with the aligned boxes they were built with); :meth:`SyntheticHouse.files` encodes the four
``house_segmentations`` files, :meth:`SyntheticHouse.habitat_files` the same house in habitat's layout
(``_semantic.ply``, ``.house``, ``.navmesh``). :func:`write_synthetic_houses` writes
``ROOT/v1/scans/<id>/house_segmentations/...`` (or the release zip), or ``ROOT/mp3d/<id>/...`` (or
``ROOT/mp3d_habitat.zip``). Everything is a pure function of the seed.
"""

from __future__ import annotations

import io
import math
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
from shapely.geometry import Polygon
from shapely.geometry import box as shapely_box

from mpchair.core.atomic import atomic_open, write_bytes
from mpchair.geometry.frames import wrap_angle
from mpchair.matterport.boxes import obb_from_aligned
from mpchair.matterport.categories import mpcat40_color, mpcat40_name, resolve_category
from mpchair.matterport.house import habitat_object_ids
from mpchair.matterport.housefile import (
    CategoryRecord,
    HouseFile,
    HouseHeader,
    ImageRecord,
    LevelRecord,
    ObjectRecord,
    PanoramaRecord,
    PortalRecord,
    RegionRecord,
    SegmentRecord,
    SurfaceRecord,
    VertexRecord,
    format_house,
)
from mpchair.matterport.jsonfiles import encode_fsegs, encode_semseg
from mpchair.matterport.navmesh import encode_navmesh
from mpchair.matterport.ply import encode_ply, encode_semantic_ply
from mpchair.synth import furniture as fu
from mpchair.synth.artifacts import apply_artifacts
from mpchair.synth.navmesh import navmesh_polygons, walkable_polygons
from mpchair.synth.primitives import Mesh, box, cbox, rect_minus_rect, rotate_z
from mpchair.synth.realism import CLEAN, DEFAULT, Realism, realism_rng

#: Raw categories used (category_mapping index, raw name with spaces, mpcat40 index). Indices below 2000 are the
#: real ``category_mapping.tsv`` rows named in the format notes; rows from 2001 on are synthetic stand-ins for
#: non-chair classes whose real row numbers we do not ship. Names containing "chair" that are NOT mpcat40 chair are
#: listed on purpose (traps for name-based filters).
CATEGORY_ROWS: tuple[tuple[int, str, int], ...] = (
    (7, "chair", 3), (25, "dining chair", 3), (29, "sofa chair", 3), (34, "armchair", 3), (85, "office chair", 3),
    (134, "desk chair", 3), (142, "swivel chair", 3), (227, "easy chair", 3), (228, "lounge chair", 3),
    (427, "recliner", 3), (488, "chaise", 3), (490, "desk and chairs", 40), (511, "row of theater chairs", 40),
    (581, "folding chair", 3), (609, "chair pillow", 8), (1466, "chair rail", 40),
    (2001, "wall", 1), (2002, "wall \\other room", 1), (2003, "floor", 2), (2004, "ceiling", 17), (2005, "window", 9),
    (2006, "stairs", 16), (2007, "railing", 30), (2008, "table", 5), (2009, "dining table", 5), (2010, "desk", 5),
    (2011, "coffee table", 5), (2012, "stool", 19), (2013, "bar stool", 19), (2014, "ottoman", 19), (2015, "sofa", 10),
    (2016, "couch", 10), (2017, "cabinet", 7), (2018, "kitchen cabinet", 7), (2019, "bed", 11), (2020, "bench", 34),
)  # fmt: skip
#: Raw categories only the realism model's clutter uses (synthetic rows, appended to the C records of houses that have
#: them, so clean houses keep their category table).
CLUTTER_ROWS: tuple[tuple[int, str, int], ...] = (
    (2021, "door", 4), (2022, "plant", 14), (2023, "potted plant", 14), (2024, "bookshelf", 31), (2025, "shelves", 31),
    (2026, "kitchen counter", 26), (2027, "cushion", 8), (2028, "pillow", 8), (2029, "box", 39), (2030, "vase", 39),
    (2031, "basket", 39), (2032, "lamp", 39), (2033, "bowl", 39),
)  # fmt: skip
_MAPPING = {name: (idx, mp) for idx, name, mp in CATEGORY_ROWS + CLUTTER_ROWS}
_CLUTTER_RAWS = frozenset(name for _, name, _ in CLUTTER_ROWS)

WALL_T = 0.12  # wall thickness
SLAB = 0.1  # floor / ceiling slab thickness
DOOR_W, DOOR_H = 0.9, 2.05
MIN_CHAIRS, MAX_CHAIRS = 10, 30


@dataclass(frozen=True, eq=False)
class SynthObject:
    """Ground truth of one synthetic object: O ``index``, ``region``, ``raw_category`` (spaces), category_mapping
    ``mapping_index``, ``mpcat40_index``/``mpcat40_name``, ``style`` (e.g. ``"office"`` for chairs, ``"wall"``) and the
    ``aligned_box (7,)`` [x, y, z_center, l, w, h, yaw] it was built with (world frame, yaw in [-pi/2, pi/2))."""

    index: int
    region: int
    raw_category: str
    mapping_index: int
    mpcat40_index: int
    mpcat40_name: str
    style: str
    aligned_box: np.ndarray


@dataclass(frozen=True, eq=False)
class SyntheticHouse:
    """A synthetic house as built: records, mesh (world frame, metres) with per-face release fields, ground truth.

    ``material_id``/``segment_id``/``category_id`` are the per-face ``.ply`` fields; ``mismatched_faces`` faces carry a
    deliberately wrong ``category_id`` (annotation drift, as in real data) so the reader's cross-check has something to
    find; ``unlabelled_faces`` belong to no object; ``realism`` is the realism it was built with.
    """

    id: str
    seed: int
    house_file: HouseFile
    vertices: np.ndarray
    faces: np.ndarray
    material_id: np.ndarray
    segment_id: np.ndarray
    category_id: np.ndarray
    colors: np.ndarray
    objects: tuple[SynthObject, ...]
    seg_groups: tuple[dict, ...]
    n_levels: int
    global_yaw: float
    global_offset: np.ndarray
    mismatched_faces: int
    unlabelled_faces: int
    realism: Realism = CLEAN

    def files(self) -> dict[str, bytes]:
        """The four ``house_segmentations`` files as ``{suffix: bytes}`` (``.house``, ``.ply``, ``.fsegs.json``,
        ``.semseg.json``), in the release format."""
        return {
            ".house": format_house(self.house_file).encode("utf-8"),
            ".ply": encode_ply(self.vertices, self.faces, self.material_id, self.segment_id, self.category_id,
                               colors=self.colors),  # fmt: skip
            ".fsegs.json": encode_fsegs(self.material_id, self.id),
            ".semseg.json": encode_semseg(self.id, list(self.seg_groups)),
        }

    def habitat_files(self) -> dict[str, bytes]:
        """The house in habitat's layout as ``{suffix: bytes}``: ``.house`` (the same file), ``_semantic.ply`` (the
        same mesh, ``object_id`` per face as habitat's converter derives it) and ``.navmesh`` (one-tile MSET version
        1, built from the floor by :mod:`mpchair.synth.navmesh`)."""
        floor_objects = [o.index for o in self.objects if o.mpcat40_index == resolve_category("floor")]
        floor = np.isin(self.segment_id, floor_objects)
        nav_vertices, polys = navmesh_polygons(walkable_polygons(self.vertices, self.faces, floor))
        return {
            ".house": format_house(self.house_file).encode("utf-8"),
            "_semantic.ply": encode_semantic_ply(self.vertices, self.faces,
                                                 habitat_object_ids(self.house_file, self.material_id),
                                                 colors=self.colors),  # fmt: skip
            ".navmesh": encode_navmesh(nav_vertices, polys),
        }


# ------------------------------------------------------------------------------------------------ scene building


@dataclass
class _Obj:
    raw: str
    region: int
    style: str
    frame_yaw: float  # house frame yaw of the object's own axes (aligned box is computed in this frame)
    frame_pos: np.ndarray
    segs: list[int] = field(default_factory=list)

    @property
    def mpcat40(self) -> int:
        return _MAPPING[self.raw][1]


@dataclass
class _Room:
    region: int
    level: int
    label: str
    rect: tuple[float, float, float, float]  # interior x0 y0 x1 y1 (house frame)
    z: float  # floor top
    obstacles: list = field(default_factory=list)

    @property
    def poly(self) -> Polygon:
        return shapely_box(*self.rect)


@dataclass(frozen=True)
class ChairMix:
    """Which chairs the room recipes put into a house.

    * ``weights``: style → weight, for a chair of no set style; ``table``: the styles drawn (uniformly) for each chair
      at a dining table; ``bedroom``: those of a bedroom's chair; ``wall``: those of the realism clutter's extra
      chairs against walls.
    * ``lounges``: chaise longues per living room, ``integers(lo, hi)``.
    * ``extra``: more chairs, ``(room labels, style, chance per room)``, put into each room after its recipe.
    * ``chaise_share``: after every room is furnished, chaise longues are added until they are this share of the
      house's chairs (0: none), one per room and round, living rooms first, then bedrooms and offices.
    * ``max_chairs``: no chair is added to a house that has this many; ``builders``: style → builder overrides
      (other sizes than :data:`furniture.CHAIR_STYLES` builds).
    """

    weights: dict[str, float]
    table: tuple[str, ...]
    lounges: tuple[int, int]
    bedroom: tuple[str, ...]
    wall: tuple[str, ...]
    extra: tuple[tuple[str, str, float], ...] = ()
    chaise_share: float = 0.0
    max_chairs: int = MAX_CHAIRS
    builders: dict[str, Callable[[np.random.Generator], list[fu.Part]]] = field(default_factory=dict)


#: The procedural recipe's chair mix (clean houses: the draws and so the bytes of the houses before the realism
#: model). Its mean chair box over many houses is MP3D's, but it gets there with few, very long chairs: 2-3 chaise
#: longues (1.55-1.95 m) in every living room against dining and office chairs of 0.5-0.7 m.
PROCEDURAL_CHAIRS = ChairMix(
    weights={name: w for name, (_, w, _) in fu.CHAIR_STYLES.items()},
    table=("dining", "dining", "armchair", "armchair", "office"), lounges=(2, 4),
    bedroom=("armchair", "dining", "folding"), wall=("dining", "dining", "office"),
)  # fmt: skip

#: The realism model's chair mix (``Realism.chair_mix``), calibrated to the mean *kept* chair box of the original
#: dataset, 0.960 x 0.667 x 0.884 m (``original-generator.md`` §8: the one statistic of its chairs there is):
#: - l - w is 0.29 m on average (l / w = 1.44), but dining, office and folding chairs and armchairs are about as deep
#:   as wide (l - w <= 0.1 m): about a quarter of the kept boxes must be chairs much longer than wide, chaise longues.
#:   Their number is a quota per house (``chaise_share`` of its chairs), spread over living rooms, bedrooms and
#:   offices, instead of 2-3 in every living room: a set of 8 houses then no longer gets its mean length from how many
#:   living rooms it has and how often the viewpoints land in them (the procedural mix: 0.93-1.02 m over seeds 0-5).
#: - indoor chaise longues, 1.4-1.75 m (1.55-1.95 m reaches into sun loungers), and armchairs 0.74-0.98 m wide
#:   (accent and club chairs; at 0.86-1.14 m, with armchairs a quarter of the kept boxes, w was 5 % over).
#: - rocking chairs (0.85-1.05 m along their rockers, 0.55-0.7 m wide: a common chair about the size of the mean box)
#:   in living rooms, bedrooms and offices, and among the chairs of no set style (fewer armchairs, no chaise there).
#: - up to 40 chairs a house: MP3D homes are big, and 30 left no room for the clutter's chairs in most houses.
MP3D_CHAIRS = ChairMix(
    weights={"dining": 0.2, "armchair": 0.3, "office": 0.12, "folding": 0.08, "rocking": 0.18},
    table=("dining", "dining", "armchair", "armchair", "office"), lounges=(0, 1),  # (0, 1): none, the quota has them
    bedroom=("armchair", "rocking", "dining", "folding"), wall=("dining", "office", "rocking", "armchair"),
    builders={"armchair": partial(fu.armchair, width=(0.74, 0.98), depth=(0.78, 0.96)),
              "lounge": partial(fu.lounge_chair, length=(1.4, 1.75))},
    extra=(("lf", "rocking", 0.6), ("b", "rocking", 0.5), ("o", "rocking", 0.3), ("o", "armchair", 0.4)),
    chaise_share=0.26, max_chairs=40,
)  # fmt: skip


class _Scene:
    """Accumulates parts (house frame), segments and objects; ``chairs`` is the house's chair mix."""

    def __init__(self, chairs: ChairMix = PROCEDURAL_CHAIRS) -> None:
        self.chairs = chairs
        self.parts: list[tuple[np.ndarray, np.ndarray, int]] = []
        self.seg_obj: list[int] = []  # object position per segment (-1 junk)
        self.seg_region: list[int] = []
        self.objs: list[_Obj] = []

    def add(self, raw: str, region: int, style: str, parts: list[fu.Part], yaw: float, pos, z: float = 0.0) -> int:
        """Add an object built in its local frame, placed at ``pos`` (x, y) / floor ``z`` with ``yaw``."""
        p = np.array([pos[0], pos[1], z], dtype=np.float64)
        obj = _Obj(raw, region, style, yaw, p)
        k = len(self.objs)
        self.objs.append(obj)
        groups: dict[int, int] = {}
        for g, v, f in parts:
            if g not in groups:
                groups[g] = len(self.seg_obj)
                self.seg_obj.append(k)
                self.seg_region.append(region)
                obj.segs.append(groups[g])
            self.parts.append((rotate_z(v, yaw) + p, f, groups[g]))
        return k

    def add_static(self, raw: str, region: int, style: str, meshes: list[Mesh]) -> int:
        """Add an object whose meshes are already in the house frame (axes aligned with the house grid)."""
        return self.add(raw, region, style, [(0, v, f) for v, f in meshes], 0.0, (0.0, 0.0))

    def add_junk(self, region: int, meshes: list[Mesh]) -> None:
        """Unlabelled geometry: a segment that belongs to no object."""
        s = len(self.seg_obj)
        self.seg_obj.append(-1)
        self.seg_region.append(region)
        for v, f in meshes:
            self.parts.append((v, f, s))

    def count(self, mpcat40: int) -> int:
        return sum(1 for o in self.objs if _MAPPING[o.raw][1] == mpcat40)


def _local_bounds(parts: list[fu.Part]) -> tuple[np.ndarray, np.ndarray]:
    allv = np.vstack([v for _, v, _ in parts])
    return allv.min(axis=0), allv.max(axis=0)


def _footprint(lo: np.ndarray, hi: np.ndarray, yaw: float, pos) -> Polygon:
    c = np.array([[lo[0], lo[1], 0], [hi[0], lo[1], 0], [hi[0], hi[1], 0], [lo[0], hi[1], 0]], dtype=np.float64)
    w = rotate_z(c, yaw)
    return Polygon(w[:, :2] + np.asarray(pos[:2]))


def _fits(room: _Room, poly: Polygon, ignore: tuple = ()) -> bool:
    if not room.poly.buffer(1e-9).contains(poly):
        return False
    return all(poly.intersection(o).area < 1e-6 for k, o in enumerate(room.obstacles) if k not in ignore)


_SIDE_YAW = (math.pi / 2, math.pi, -math.pi / 2, 0.0)  # facing into the room from walls y0, x1, y1, x0


def _wall_pose(room: _Room, lo, hi, side: int, u: float, gap: float) -> tuple[float, np.ndarray]:
    """Pose that puts the object's back (local -x face) against wall ``side`` at fraction ``u`` along it."""
    x0, y0, x1, y1 = room.rect
    yaw = _SIDE_YAW[side]
    half_w = (hi[1] - lo[1]) / 2
    if side in (0, 2):
        along = x0 + half_w + u * max(0.0, (x1 - x0) - 2 * half_w)
        target = np.array([along, y0 + gap if side == 0 else y1 - gap])
    else:
        along = y0 + half_w + u * max(0.0, (y1 - y0) - 2 * half_w)
        target = np.array([x1 - gap if side == 1 else x0 + gap, along])
    back_mid = rotate_z(np.array([[lo[0], (lo[1] + hi[1]) / 2, 0.0]]), yaw)[0, :2]
    return yaw, target - back_mid


def _place_wall(scene, room, rng, raw, style, parts, gap=0.03, tries=25, register=True) -> int | None:
    lo, hi = _local_bounds(parts)
    for _ in range(tries):
        side = int(rng.integers(4))
        yaw, pos = _wall_pose(room, lo, hi, side, float(rng.random()), gap)
        poly = _footprint(lo, hi, yaw, pos)
        if _fits(room, poly):
            if register:
                room.obstacles.append(poly)
            return scene.add(raw, room.region, style, parts, yaw, pos, room.z)
    return None


def _place_free(scene, room, rng, raw, style, parts, tries=25, yaw=None, near=None) -> int | None:
    lo, hi = _local_bounds(parts)
    x0, y0, x1, y1 = room.rect
    for _ in range(tries):
        a = float(rng.uniform(0, 2 * math.pi)) if yaw is None else yaw
        if near is None:
            c = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
        else:
            c = np.asarray(near) + rng.normal(0, 0.3, 2)
        pos = c - rotate_z(np.array([[(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, 0.0]]), a)[0, :2]
        poly = _footprint(lo, hi, a, pos)
        if _fits(room, poly):
            room.obstacles.append(poly)
            return scene.add(raw, room.region, style, parts, a, pos, room.z)
    return None


def _random_chair(rng: np.random.Generator, mix: ChairMix, style: str | None = None) -> tuple[str, str, list[fu.Part]]:
    """A chair of ``style`` (or one drawn by ``mix.weights``): its style, raw category and parts."""
    if style is None:
        names = list(mix.weights)
        w = np.array([mix.weights[n] for n in names])
        style = names[int(rng.choice(len(names), p=w / w.sum()))]
    builder, _, raws = (fu.CHAIR_STYLES | fu.REALISM_CHAIR_STYLES)[style]
    raw = raws[int(rng.integers(len(raws)))][1]
    return style, raw, mix.builders.get(style, builder)(rng)


def _chair_room_left(scene: _Scene) -> bool:
    return scene.count(3) < scene.chairs.max_chairs


def _table_with_chairs(scene, room, rng, kind="dining", n_chairs=(4, 7)) -> None:
    parts = fu.table(rng, kind)
    lo, hi = _local_bounds(parts)
    x0, y0, x1, y1 = room.rect
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    base_yaw = float(rng.choice([0.0, math.pi / 2])) + float(rng.uniform(-0.35, 0.35))
    t_idx = _place_free(scene, room, rng, "dining table" if kind == "dining" else "table", "table", parts,
                        yaw=base_yaw, near=centre)  # fmt: skip
    if t_idx is None:
        return
    t_obj = scene.objs[t_idx]
    t_poly_k = len(room.obstacles) - 1
    tl, tw = hi[0] - lo[0], hi[1] - lo[1]
    n = int(rng.integers(n_chairs[0], n_chairs[1] + 1))
    slots = []
    per_side = max(1, min(3, int(tl / 0.6)))
    for sgn in (-1, 1):
        for k in range(per_side):
            slots.append((sgn, (k + 0.5) / per_side - 0.5))
    if tl > 1.3:
        slots += [(2, 0.0), (-2, 0.0)]  # ends
    order = rng.permutation(len(slots))
    for k in order[:n]:
        if not _chair_room_left(scene):
            return
        side, frac = slots[k]
        # Upholstered armchairs at tables are common in real homes, and the mix sets the mean chair box (MP3D's is
        # 0.96 x 0.67 x 0.88 m, long because of armchairs and lounge chairs).
        pick = str(rng.choice(list(scene.chairs.table)))
        style, raw, cparts = _random_chair(rng, scene.chairs, pick)
        clo, chi = _local_bounds(cparts)
        depth = chi[0] - clo[0]
        pushed = rng.random() < 0.45
        if abs(side) == 1:
            normal = np.array([0.0, float(side)])  # table-local direction from the table to the chair
            along = np.array([frac * tl, 0.0])
            edge = tw / 2
        else:
            normal = np.array([float(np.sign(side)), 0.0])
            along = np.array([0.0, 0.0])
            edge = tl / 2
        # Distance of the chair's AABB centre from the table centre: in front of the edge, or pushed under it.
        dist = edge - depth * float(rng.uniform(0.15, 0.35)) + depth / 2 if pushed else edge + depth / 2 + 0.08
        c_local = along + normal * dist + np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2])
        c_house = rotate_z(np.array([[c_local[0], c_local[1], 0.0]]), t_obj.frame_yaw)[0, :2] + t_obj.frame_pos[:2]
        face_dir = -normal
        yaw = t_obj.frame_yaw + math.atan2(face_dir[1], face_dir[0]) + float(rng.uniform(-0.15, 0.15))
        pos = c_house - rotate_z(np.array([[(clo[0] + chi[0]) / 2, (clo[1] + chi[1]) / 2, 0.0]]), yaw)[0, :2]
        poly = _footprint(clo, chi, yaw, pos)
        if _fits(room, poly, ignore=(t_poly_k,) if pushed else ()):
            room.obstacles.append(poly)
            scene.add(raw, room.region, style, cparts, yaw, pos, room.z)


def _wall_chair(scene, room, rng, style=None) -> None:
    if _chair_room_left(scene):
        style, raw, parts = _random_chair(rng, scene.chairs, style)
        _place_wall(scene, room, rng, raw, style, parts, gap=float(rng.uniform(0.02, 0.15)))


def _free_chair(scene, room, rng, style=None) -> None:
    if _chair_room_left(scene):
        style, raw, parts = _random_chair(rng, scene.chairs, style)
        # A room too full for a free-standing chair may still have a free stretch of wall.
        if _place_free(scene, room, rng, raw, style, parts) is None:
            _place_wall(scene, room, rng, raw, style, parts, gap=float(rng.uniform(0.02, 0.15)))


def _desk_with_chair(scene: _Scene, room: _Room, rng: np.random.Generator) -> None:
    """A desk against a wall and, room for chairs left, an office chair facing it, its seat partly under the desk."""
    desk = [(g, rotate_z(v, math.pi / 2), f) for g, v, f in fu.table(rng, "desk")]
    d_idx = _place_wall(scene, room, rng, "desk", "table", desk, gap=0.02)
    if d_idx is not None and _chair_room_left(scene):
        d = scene.objs[d_idx]
        style, raw, parts = _random_chair(rng, scene.chairs, "office")
        clo, chi = _local_bounds(parts)
        dlo, dhi = _local_bounds(desk)
        reach = dhi[0] + (chi[0] - clo[0]) * float(rng.uniform(0.1, 0.45))
        c = rotate_z(np.array([[reach, 0.0, 0.0]]), d.frame_yaw)[0, :2] + d.frame_pos[:2]
        yaw = d.frame_yaw + math.pi + float(rng.uniform(-0.4, 0.4))
        pos = c - rotate_z(np.array([[(clo[0] + chi[0]) / 2, (clo[1] + chi[1]) / 2, 0.0]]), yaw)[0, :2]
        poly = _footprint(clo, chi, yaw, pos)
        if _fits(room, poly, ignore=(len(room.obstacles) - 1,)):
            room.obstacles.append(poly)
            scene.add(raw, room.region, style, parts, yaw, pos, room.z)


def _furnish(scene: _Scene, room: _Room, rng: np.random.Generator) -> None:
    """Furnish one room by its type (``d`` dining, ``k`` kitchen, ``l`` / ``f`` living, ``o`` office, ``b`` bedroom,
    ``a`` bath, ``h`` hallway), then the chair mix's ``extra`` chairs."""
    lab = room.label
    if lab == "d":
        _table_with_chairs(scene, room, rng, "dining", (4, 8))
        _place_wall(scene, room, rng, "cabinet", "cabinet", fu.cabinet(rng))
        if rng.random() < 0.6:
            x0, y0, x1, y1 = room.rect
            span = min(x1 - x0, y1 - y0) - 1.4
            _place_wall(scene, room, rng, "chair rail", "rail", fu.chair_rail(span), gap=0.0, register=False)
        _wall_chair(scene, room, rng)
    elif lab == "k":
        for _ in range(int(rng.integers(1, 3))):
            _place_wall(scene, room, rng, "kitchen cabinet", "cabinet", fu.cabinet(rng, tall=rng.random() < 0.3))
        if rng.random() < 0.6:
            _table_with_chairs(scene, room, rng, "dining", (2, 4))
        for _ in range(int(rng.integers(1, 3))):
            _place_free(scene, room, rng, "bar stool", "stool", fu.stool(rng, "bar"))
    elif lab in ("l", "f"):
        _place_wall(scene, room, rng, str(rng.choice(["sofa", "couch"])), "sofa", fu.sofa(rng))
        _place_free(scene, room, rng, "coffee table", "table", fu.table(rng, "coffee"))
        # Lounge chairs first: at 1.55-1.95 m they rarely fit once the armchairs are down, and they (with the
        # armchairs) are what makes the mean chair box as long as MP3D's (0.96 x 0.67 x 0.88 m).
        for _ in range(int(rng.integers(*scene.chairs.lounges))):
            _free_chair(scene, room, rng, "lounge")
        for _ in range(int(rng.integers(1, 3))):
            _free_chair(scene, room, rng, "armchair")
        if rng.random() < 0.5:
            _place_free(scene, room, rng, "ottoman", "stool", fu.stool(rng, "ottoman"))
        _wall_chair(scene, room, rng)
    elif lab == "o":
        _desk_with_chair(scene, room, rng)
        _place_wall(scene, room, rng, "cabinet", "cabinet", fu.cabinet(rng, tall=True))
        if rng.random() < 0.5:
            _free_chair(scene, room, rng, "office")
        _wall_chair(scene, room, rng, "folding" if rng.random() < 0.4 else None)
    elif lab == "b":
        _place_wall(scene, room, rng, "bed", "bed", fu.bed(rng), gap=0.01)
        _place_wall(scene, room, rng, "cabinet", "cabinet", fu.cabinet(rng, tall=rng.random() < 0.5))
        _wall_chair(scene, room, rng, str(rng.choice(list(scene.chairs.bedroom))))
    elif lab == "a":
        _place_wall(scene, room, rng, "cabinet", "cabinet", fu.cabinet(rng))
        _place_free(scene, room, rng, "stool", "stool", fu.stool(rng, "bar"))
    elif lab == "h":
        _place_wall(scene, room, rng, "bench", "bench", fu.bench(rng))
        _wall_chair(scene, room, rng, "folding" if rng.random() < 0.5 else None)
    for labels, style, chance in scene.chairs.extra:
        if lab in labels and rng.random() < chance:
            _extra_chair(scene, room, rng, style)


def _add_chaises(scene: _Scene, rooms: list[_Room], rng: np.random.Generator) -> None:
    """Chaise longues until they are ``scene.chairs.chaise_share`` of the house's chairs (none when 0): one per room
    and round, living and family rooms first, then bedrooms and offices, then the others."""
    share = scene.chairs.chaise_share
    if share <= 0:
        return
    want = int(round(share * scene.count(3) / (1 - share)))
    rank = {"l": 0, "f": 0, "b": 1, "o": 1}
    order = sorted(rooms, key=lambda r: (rank.get(r.label, 2), float(rng.random())))
    placed = 0
    for _ in range(3):
        for room in order:
            if placed >= want or not _chair_room_left(scene):
                return
            n = len(scene.objs)
            _extra_chair(scene, room, rng, "lounge")
            placed += len(scene.objs) > n


def _extra_chair(scene: _Scene, room: _Room, rng: np.random.Generator, style: str) -> None:
    """One of the chair mix's ``extra`` chairs: free-standing, else against a wall, a chaise longue then lengthwise
    along it (where real rooms keep one: a full room has no free 1.6-1.9 m of floor in front of a wall)."""
    if not _chair_room_left(scene):
        return
    style, raw, parts = _random_chair(rng, scene.chairs, style)
    if _place_free(scene, room, rng, raw, style, parts) is None:
        if style == "lounge":
            parts = [(g, rotate_z(v, math.pi / 2), f) for g, v, f in parts]
        _place_wall(scene, room, rng, raw, style, parts, gap=float(rng.uniform(0.02, 0.15)))


# ------------------------------------------------------------------------------------------------ clutter


def _top_of(scene: _Scene, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Object ``k``'s parts' extent ``(lo, hi)`` in its own frame (for things put on top of it)."""
    o = scene.objs[k]
    verts = np.vstack([v for v, _, s in scene.parts if s in o.segs])
    local = rotate_z(verts - o.frame_pos, -o.frame_yaw)
    return local.min(axis=0), local.max(axis=0)


def _put_on(scene: _Scene, k: int, rng: np.random.Generator, raw: str, style: str, parts: list[fu.Part],
            margin: float = 0.05, top: float | None = None) -> None:
    """Put ``parts`` on object ``k``'s top (or at local height ``top``), inside its footprint less ``margin``."""
    o = scene.objs[k]
    lo, hi = _top_of(scene, k)
    plo, phi = _local_bounds(parts)
    half = (phi[:2] - plo[:2]) / 2 + margin
    if np.any(hi[:2] - lo[:2] < 2 * half):
        return
    c = rng.uniform(lo[:2] + half, hi[:2] - half)
    pos = rotate_z(np.array([[c[0], c[1], 0.0]]), o.frame_yaw)[0, :2] + o.frame_pos[:2]
    z = o.frame_pos[2] + (hi[2] if top is None else top)
    scene.add(raw, o.region, style, parts, o.frame_yaw + float(rng.uniform(-0.4, 0.4)), pos, z)


def _door_leaves(scene: _Scene, rooms: list[_Room], portals, realism: Realism, rng: np.random.Generator) -> None:
    """An open door leaf in a door opening (``realism.doors`` per door), swung 65-95 deg into one of its rooms, in the
    free zone kept in front of every door."""
    for a, b, (lo, hi) in portals:
        if rng.random() >= realism.doors:
            continue
        region = a if b < 0 or rng.random() < 0.5 else b
        room = rooms[region]
        across = 0 if hi[0] - lo[0] < hi[1] - lo[1] else 1  # the wall's thin axis
        along = 1 - across
        rc = (room.rect[across] + room.rect[across + 2]) / 2
        into = 1.0 if rc > (lo[across] + hi[across]) / 2 else -1.0
        hinge = np.zeros(2)
        hinge[across] = hi[across] if into > 0 else lo[across]
        hinge[along] = lo[along] + 0.02
        theta = math.radians(float(rng.uniform(65, 95)))
        d = np.zeros(2)
        d[along], d[across] = math.cos(theta), into * math.sin(theta)
        width, height = hi[along] - lo[along] - 0.04, hi[2] - lo[2] - 0.02
        if width > 1.0:  # an open-plan opening, not a door
            continue
        scene.add("door", region, "door", fu.door_leaf(width, height), math.atan2(d[1], d[0]), hinge, room.z)


def _add_clutter(scene: _Scene, rooms: list[_Room], portals, realism: Realism, rng: np.random.Generator) -> None:
    """The realism model's clutter (``realism.clutter`` scales the counts) and door leaves, drawn from ``rng``."""
    if realism.doors > 0:
        _door_leaves(scene, rooms, portals, realism, rng)
    if realism.clutter <= 0:
        return

    def count(mean: float) -> int:
        return int(rng.poisson(mean * realism.clutter))

    for room in rooms:
        if room.label == "s":
            continue
        lab = room.label
        n_objs = len(scene.objs)
        for _ in range(count(1.0)):
            raw = str(rng.choice(["plant", "potted plant"]))
            _place_wall(scene, room, rng, raw, "plant", fu.plant(rng), gap=0.05)
        for _ in range(count(0.9 if lab in ("l", "f", "o", "b", "h") else 0.3)):
            _place_wall(scene, room, rng, str(rng.choice(["bookshelf", "shelves"])), "shelving", fu.shelving(rng),
                        gap=0.01)  # fmt: skip
        if lab == "k":
            for _ in range(1 + count(1.0)):
                _place_wall(scene, room, rng, "kitchen counter", "counter", fu.counter(rng), gap=0.0)
        for _ in range(count(0.3 if lab in ("k", "d", "h", "o") else 0.1)):
            style, raw, parts = "stool", "chair", fu.stool_chair(rng)
            if _chair_room_left(scene) and _place_free(scene, room, rng, raw, style, parts) is None:
                _place_wall(scene, room, rng, raw, style, parts, gap=float(rng.uniform(0.02, 0.15)))
        # More chairs against walls (the mix's ``wall`` kinds): real rooms hold more chairs than the recipe's.
        for _ in range(count(0.7)):
            _wall_chair(scene, room, rng, str(rng.choice(list(scene.chairs.wall))))
        for _ in range(count(2.0)):
            raw = str(rng.choice(["box", "basket", "vase", "lamp"]))
            _place_wall(scene, room, rng, raw, "object", fu.small_object(rng), gap=float(rng.uniform(0.0, 0.3)))
        # Things on tables, counters, cabinets and beds (their tops, not the floor).
        hosts = [k for k in range(n_objs) if scene.objs[k].region == room.region
                 and scene.objs[k].style in ("table", "counter", "cabinet", "bed")]  # fmt: skip
        for k in hosts:
            for _ in range(count(1.5 if scene.objs[k].style != "bed" else 1.0)):
                if scene.objs[k].style == "bed":
                    _put_on(scene, k, rng, str(rng.choice(["cushion", "pillow"])), "cushion", fu.cushion(rng), 0.1)
                else:
                    _put_on(scene, k, rng, str(rng.choice(["box", "vase", "lamp", "bowl"])), "object",
                            fu.small_object(rng))  # fmt: skip


# ------------------------------------------------------------------------------------------------ structure


@dataclass
class _Opening:
    u0: float
    u1: float
    z0: float
    z1: float
    kind: str  # door | window


def _wall_meshes(orient: str, coord: float, a0: float, a1: float, z: float, height: float, openings) -> list[Mesh]:
    """Closed boxes for one wall (centred on grid line ``coord``) from ``a0`` to ``a1``, minus its openings."""
    t = WALL_T / 2
    spans = []  # (u0, u1, z0, z1) in edge coordinates
    cur = a0 - t
    for op in sorted(openings, key=lambda o: o.u0):
        spans.append((cur, op.u0, 0.0, height))
        if op.z0 > 0:
            spans.append((op.u0, op.u1, 0.0, op.z0))
        if op.z1 < height:
            spans.append((op.u0, op.u1, op.z1, height))
        cur = op.u1
    spans.append((cur, a1 + t, 0.0, height))
    out = []
    for u0, u1, z0, z1 in spans:
        if u1 - u0 < 1e-6 or z1 - z0 < 1e-6:
            continue
        if orient == "v":  # x = coord, running along y
            out.append(box((coord - t, u0, z + z0), (coord + t, u1, z + z1)))
        else:
            out.append(box((u0, coord - t, z + z0), (u1, coord + t, z + z1)))
    return out


def _window_meshes(orient: str, coord: float, op: _Opening, z: float) -> list[Mesh]:
    """A window frame inside the wall opening: sill (protruding), head and two jambs."""
    t = WALL_T / 2 + 0.02
    f = 0.05
    pieces = [
        (op.u0, op.u1, op.z0 - 0.0, op.z0 + 0.04, t + 0.04),
        (op.u0, op.u1, op.z1 - f, op.z1, t),
        (op.u0, op.u0 + f, op.z0, op.z1, t),
        (op.u1 - f, op.u1, op.z0, op.z1, t),
    ]
    out = []
    for u0, u1, z0, z1, th in pieces:
        if orient == "v":
            out.append(box((coord - th, u0, z + z0), (coord + th, u1, z + z1)))
        else:
            out.append(box((u0, coord - th, z + z0), (u1, coord + th, z + z1)))
    return out


def _hex_id(rng: np.random.Generator, n: int = 32) -> str:
    return "".join("0123456789abcdef"[int(k)] for k in rng.integers(0, 16, n))


_ID_CHARS = "0123456789ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz"


def make_house_id(rng: np.random.Generator) -> str:
    """An 11-character scan id like the real ones (e.g. ``17DRP5sb8fy``)."""
    return "".join(_ID_CHARS[int(k)] for k in rng.integers(0, len(_ID_CHARS), 11))


@dataclass(frozen=True, eq=False)
class _Grid:
    """The house's room grid (house frame, metres): ``nc`` x ``nr`` cells per level between the grid lines ``xs`` /
    ``ys``, ``n_levels`` levels with floors at ``level_z`` (``level_h`` apart), rooms ``ceil_h`` high, and the
    ``stair_cell`` ``(i, j)`` that holds the stair when there are two levels."""

    nc: int
    nr: int
    xs: np.ndarray
    ys: np.ndarray
    n_levels: int
    ceil_h: float
    level_h: float
    level_z: list[float]
    stair_cell: tuple[int, int]


@dataclass(frozen=True, eq=False)
class _Layout:
    """The rooms of a house on its ``grid``: ``rooms`` in region order and ``cell_region[(level, i, j)]``, the region
    of each grid cell."""

    grid: _Grid
    rooms: list[_Room]
    cell_region: dict[tuple[int, int, int], int]


def synthesize_house(seed: int, house_id: str | None = None, *, levels: int | None = None,
                     realism: Realism = DEFAULT) -> SyntheticHouse:
    """Build one procedural house from ``seed`` (see module docstring). ``levels`` forces 1 or 2 levels; ``realism``
    sets the reconstruction artifacts and clutter (:mod:`mpchair.synth.realism`; ``CLEAN``: none).

    Deterministic: the same ``seed``, ``house_id``, ``levels`` and ``realism`` give the same house, bit for bit.
    Every step draws from ``rng`` (the recipe) or ``rrng`` (the realism model) in a fixed order: reordering the steps
    changes the houses.
    """
    rng = np.random.default_rng(seed)
    rrng = realism_rng(seed)
    if house_id is None:
        house_id = make_house_id(rng)
    n_levels = int(levels) if levels is not None else int(rng.integers(1, 3))
    if n_levels not in (1, 2):
        raise ValueError("levels must be 1 or 2")
    layout = _lay_out_rooms(_draw_grid(rng, rrng, n_levels, realism), rng)
    scene = _Scene(MP3D_CHAIRS if realism.chair_mix else PROCEDURAL_CHAIRS)
    stair = _add_stair(scene, layout)
    portals = _add_walls(scene, layout, realism, rng, rrng)
    _add_slabs(scene, layout, stair, rng)
    _furnish_house(scene, layout.rooms, rng)
    _add_junk(scene, layout.rooms, rng)
    _add_clutter(scene, layout.rooms, portals, realism, rrng)
    truth = _true_extents(scene)  # the true boxes, measured before any reconstruction artifact
    if not realism.is_clean:
        scene.parts = apply_artifacts(scene, layout.rooms, truth, realism, rrng, wall_t=WALL_T, slab=SLAB)
    pose = _Pose(yaw=float(rng.uniform(0, 2 * math.pi)),
                 offset=np.array([rng.uniform(-25, 25), rng.uniform(-25, 25), rng.uniform(-1.5, 1.5)]))
    return _finish(scene, layout, portals, truth, pose, rng, house_id=house_id, seed=int(seed), realism=realism)


def _draw_grid(rng: np.random.Generator, rrng: np.random.Generator, n_levels: int, realism: Realism) -> _Grid:
    """The grid: 2-3 x 2 cells of 3.4-5.2 x 3.4-4.8 m (``realism.room_size``: scaled to that mean size), a stair cell
    at least 4.2 m long when there are two levels, a ceiling 2.5-2.8 m high."""
    nc, nr = int(rng.integers(2, 4)), 2
    cw = rng.uniform(3.4, 5.2, nc)
    rd = rng.uniform(3.4, 4.8, nr)
    if realism.room_size > 0:  # larger rooms, of about the same mean size in every house (steadier scan density)
        size = realism.room_size
        if realism.room_size_spread > 0:  # homes differ in size: the density's tail (its max) is that of bigger homes
            size *= 1 + realism.room_size_spread * float(rrng.uniform(-1, 1))
        k = size / float(np.mean(np.concatenate([cw, rd])))
        cw, rd = cw * k, rd * k
    stair_cell = (int(rng.integers(nc)), int(rng.integers(nr)))
    if n_levels == 2 and max(cw[stair_cell[0]], rd[stair_cell[1]]) < 4.2:
        cw[stair_cell[0]] = rng.uniform(4.2, 4.8)
    xs = np.concatenate([[0.0], np.cumsum(cw)])
    ys = np.concatenate([[0.0], np.cumsum(rd)])
    ceil_h = float(rng.uniform(2.5, 2.8))
    level_h = ceil_h + 0.3
    return _Grid(nc=nc, nr=nr, xs=xs, ys=ys, n_levels=n_levels, ceil_h=ceil_h, level_h=level_h,
                 level_z=[0.0, level_h][:n_levels], stair_cell=stair_cell)


def _lay_out_rooms(grid: _Grid, rng: np.random.Generator) -> _Layout:
    """A room per grid cell and level, labelled by a shuffle of each level's room types (the stair cell: ``s``
    below, a hallway ``h`` above); interiors inset by half a wall."""
    rooms: list[_Room] = []
    labels0 = list(rng.permutation(["d", "l", "k", "o", "f", "d"]))
    labels1 = list(rng.permutation(["b", "b", "a", "o", "b", "l"]))
    cell_region: dict[tuple[int, int, int], int] = {}
    xs, ys = grid.xs, grid.ys
    for lv in range(grid.n_levels):
        pool = labels0 if lv == 0 else labels1
        for j in range(grid.nr):
            for i in range(grid.nc):
                if grid.n_levels == 2 and (i, j) == grid.stair_cell:
                    lab = "s" if lv == 0 else "h"
                else:
                    lab = str(pool.pop(0))
                m = WALL_T / 2
                rect = (xs[i] + m, ys[j] + m, xs[i + 1] - m, ys[j + 1] - m)
                cell_region[(lv, i, j)] = len(rooms)
                rooms.append(_Room(len(rooms), lv, lab, rect, grid.level_z[lv]))
    return _Layout(grid=grid, rooms=rooms, cell_region=cell_region)


def _add_stair(scene: _Scene, layout: _Layout) -> tuple | None:
    """A straight stair run (two levels only) inside the stair cell, along its longer side against one wall, the floor
    opening above it and a railing along the opening's open long side. Returns ``(steps, opening x0 y0 x1 y1,
    along_x)`` (house frame), or None for one level."""
    grid = layout.grid
    if grid.n_levels != 2:
        return None
    si, sj = grid.stair_cell
    r0 = layout.rooms[layout.cell_region[(0, si, sj)]]
    x0, y0, x1, y1 = r0.rect
    n_steps = 15
    rise = grid.level_h / n_steps
    along_x = (x1 - x0) >= (y1 - y0)
    span = (x1 - x0) if along_x else (y1 - y0)
    going = min(0.26, (span - 0.4) / n_steps)
    sw = 0.95
    steps = []
    for k in range(n_steps):
        a = 0.2 + k * going
        if along_x:
            steps.append(box((x0 + a, y0, 0.0), (x0 + a + going, y0 + sw, (k + 1) * rise)))
        else:
            steps.append(box((x0, y0 + a, 0.0), (x0 + sw, y0 + a + going, (k + 1) * rise)))
    end = 0.2 + n_steps * going
    hole = (x0 + 0.2, y0 - 0.1, x0 + end, y0 + sw + 0.05) if along_x else (x0 - 0.1, y0 + 0.2, x0 + sw + 0.05,
                                                                            y0 + end)  # fmt: skip
    scene.add_static("stairs", r0.region, "stairs", steps)
    r0.obstacles.append(shapely_box(hole[0], hole[1], hole[2], hole[3]).buffer(0.6))
    r1 = layout.rooms[layout.cell_region[(1, si, sj)]]
    r1.obstacles.append(shapely_box(*hole).buffer(0.3))
    z1 = grid.level_z[1]
    if along_x:
        rail = [box((hole[0], hole[3], z1 + 0.95), (hole[2], hole[3] + 0.05, z1 + 1.0))]
        rail += [box((x, hole[3], z1), (x + 0.04, hole[3] + 0.04, z1 + 0.95)) for x in
                 np.linspace(hole[0], hole[2] - 0.04, 5)]  # fmt: skip
    else:
        rail = [box((hole[2], hole[1], z1 + 0.95), (hole[2] + 0.05, hole[3], z1 + 1.0))]
        rail += [box((hole[2], y, z1), (hole[2] + 0.04, y + 0.04, z1 + 0.95)) for y in
                 np.linspace(hole[1], hole[3] - 0.04, 5)]  # fmt: skip
    scene.add_static("railing", r1.region, "railing", rail)
    return steps, hole, along_x


def _grid_edges(grid: _Grid) -> list[tuple[str, float, float, float, list[tuple[int, int]]]]:
    """Every wall of one level: ``(orient, coord, a0, a1, cells)``, ``"v"`` at x = coord from y = a0 to a1 or ``"h"``
    at y = coord, and the one (outer wall) or two grid cells it bounds."""
    xs, ys, nc, nr = grid.xs, grid.ys, grid.nc, grid.nr
    edges = []
    for i in range(nc + 1):
        for j in range(nr):
            cells = [c for c in ((i - 1, j), (i, j)) if 0 <= c[0] < nc]
            edges.append(("v", xs[i], ys[j], ys[j + 1], cells))
    for j in range(nr + 1):
        for i in range(nc):
            cells = [c for c in ((i, j - 1), (i, j)) if 0 <= c[1] < nr]
            edges.append(("h", ys[j], xs[i], xs[i + 1], cells))
    return edges


def _add_walls(scene: _Scene, layout: _Layout, realism: Realism, rng: np.random.Generator,
               rrng: np.random.Generator) -> list[tuple[int, int, np.ndarray]]:
    """Walls, doors (between rooms and one entry door) and windows (outer walls), per level; returns the portals
    ``(region0, region1 or -1, house-frame AABB lo/hi (2, 3))``."""
    grid = layout.grid
    portals: list[tuple[int, int, np.ndarray]] = []
    wall_raw_trap_done = False
    for lv in range(grid.n_levels):
        z = grid.level_z[lv]
        edges = _grid_edges(grid)
        exterior = [k for k, e in enumerate(edges) if len(e[4]) == 1]
        entry = int(rng.choice(exterior)) if lv == 0 else -1
        for k, (orient, coord, a0, a1, cells) in enumerate(edges):
            ops = _wall_openings(a0, a1, len(cells) == 2, k == entry, grid.ceil_h, realism, rng, rrng)
            regions = [layout.cell_region[(lv, c[0], c[1])] for c in cells]
            raw = "wall"
            if not wall_raw_trap_done and len(cells) == 1:
                raw, wall_raw_trap_done = "wall \\other room", True
            scene.add_static(raw, regions[0], "wall", _wall_meshes(orient, coord, a0, a1, z, grid.ceil_h, ops))
            for op in ops:
                t = WALL_T / 2
                if orient == "v":
                    lo, hi = (coord - t, op.u0, z + op.z0), (coord + t, op.u1, z + op.z1)
                else:
                    lo, hi = (op.u0, coord - t, z + op.z0), (op.u1, coord + t, z + op.z1)
                if op.kind == "door":
                    portals.append((regions[0], regions[1] if len(regions) > 1 else -1, np.array([lo, hi])))
                    for c, rg in zip(cells, regions):  # keep the floor in front of each door free
                        layout.rooms[rg].obstacles.append(_door_zone(grid, orient, coord, op, c))
                else:
                    scene.add_static("window", regions[0], "window", _window_meshes(orient, coord, op, z))
    return portals


def _wall_openings(a0: float, a1: float, inner: bool, entry: bool, ceil_h: float, realism: Realism,
                   rng: np.random.Generator, rrng: np.random.Generator) -> list[_Opening]:
    """The openings of the wall from ``a0`` to ``a1``: a door in an ``inner`` wall (with ``realism.open_plan``: a
    wide opening instead) and in the ``entry`` wall, else a window (chance 0.7)."""
    length = a1 - a0
    ops: list[_Opening] = []
    if inner or entry:
        u = float(rng.uniform(a0 + 0.6 + DOOR_W / 2, a1 - 0.6 - DOOR_W / 2))
        dw = DOOR_W
        if inner and realism.open_plan > 0 and rrng.random() < realism.open_plan:
            # Open plan: a wide opening instead of a door (long sightlines into the next room).
            dw = float(rrng.uniform(1.6, length - 1.2))
            u = float(rrng.uniform(a0 + 0.6 + dw / 2, a1 - 0.6 - dw / 2))
        ops.append(_Opening(u - dw / 2, u + dw / 2, 0.0, DOOR_H, "door"))
    elif rng.random() < 0.7:
        ww = float(rng.uniform(1.0, min(1.8, length - 1.4)))
        u = float(rng.uniform(a0 + 0.6 + ww / 2, a1 - 0.6 - ww / 2))
        ops.append(_Opening(u - ww / 2, u + ww / 2, 0.9, min(2.1, ceil_h - 0.25), "window"))
    return ops


def _door_zone(grid: _Grid, orient: str, coord: float, op: _Opening, cell: tuple[int, int]) -> Polygon:
    """The floor kept free in front of door ``op`` on the side of grid ``cell``: 1 m deep, 0.1 m wider each side."""
    if orient == "v":
        side = 1 if cell[0] == int(np.searchsorted(grid.xs, coord)) - 1 else -1
        return shapely_box(min(coord, coord - side * 1.0), op.u0 - 0.1, max(coord, coord - side * 1.0), op.u1 + 0.1)
    side = 1 if cell[1] == int(np.searchsorted(grid.ys, coord)) - 1 else -1
    return shapely_box(op.u0 - 0.1, min(coord, coord - side * 1.0), op.u1 + 0.1, max(coord, coord - side * 1.0))


def _add_slabs(scene: _Scene, layout: _Layout, stair: tuple | None, rng: np.random.Generator) -> None:
    """Floors and ceilings; the stair opening cuts the upper floor and the lower ceiling; a top-level ceiling has an
    unreconstructed hole (rays escape through it, like holes in real scans)."""
    grid, rooms = layout.grid, layout.rooms
    xs, ys, ceil_h = grid.xs, grid.ys, grid.ceil_h
    top_rooms = [r for r in rooms if r.level == grid.n_levels - 1 and r.label != "h"]
    hole_room = top_rooms[int(rng.integers(len(top_rooms)))].region
    for room in rooms:
        i, j = next((c[1], c[2]) for c, rg in layout.cell_region.items() if rg == room.region)
        cell = (xs[i], ys[j], xs[i + 1], ys[j + 1])
        z = room.z
        floor_rects = [cell]
        ceil_rects = [cell]
        if stair is not None and (i, j) == grid.stair_cell:
            if room.level == 1:
                floor_rects = rect_minus_rect(cell, stair[1])
            else:
                ceil_rects = rect_minus_rect(cell, stair[1])
        if room.region == hole_room:
            x0, y0, x1, y1 = room.rect
            hw, hd = rng.uniform(0.7, 1.4, 2)
            hx = float(rng.uniform(x0 + 0.5, x1 - 0.5 - hw))
            hy = float(rng.uniform(y0 + 0.5, y1 - 0.5 - hd))
            ceil_rects = [r for c in ceil_rects for r in rect_minus_rect(c, (hx, hy, hx + hw, hy + hd))]
        floors = [box((a, b, z - SLAB), (c, d, z)) for a, b, c, d in floor_rects]
        scene.add_static("floor", room.region, "floor", floors)
        scene.add_static("ceiling", room.region, "ceiling",
                         [box((a, b, z + ceil_h), (c, d, z + ceil_h + SLAB)) for a, b, c, d in ceil_rects])  # fmt: skip


def _furnish_house(scene: _Scene, rooms: list[_Room], rng: np.random.Generator) -> None:
    """Furniture by room type, the chair mix's chaise longues, then chairs (against walls or free-standing in random
    rooms) until the house has :data:`MIN_CHAIRS`."""
    for room in rooms:
        if room.label != "s":
            _furnish(scene, room, rng)
    furnishable = [r for r in rooms if r.label != "s"]
    _add_chaises(scene, furnishable, rng)
    for _ in range(60):
        if scene.count(3) >= MIN_CHAIRS:
            break
        room = furnishable[int(rng.integers(len(furnishable)))]
        if rng.random() < 0.5:
            _wall_chair(scene, room, rng)
        else:
            _free_chair(scene, room, rng)


def _add_junk(scene: _Scene, rooms: list[_Room], rng: np.random.Generator) -> None:
    """A few unlabelled fragments (floating debris and a loose panel), as real scans have."""
    for _ in range(int(rng.integers(2, 5))):
        room = rooms[int(rng.integers(len(rooms)))]
        x0, y0, x1, y1 = room.rect
        c = np.array([rng.uniform(x0 + 0.3, x1 - 0.3), rng.uniform(y0 + 0.3, y1 - 0.3), room.z + rng.uniform(1.9, 2.3)])
        s = rng.uniform(0.05, 0.2, 3)
        scene.add_junk(room.region, [cbox(*c, *s)])


def _true_extents(scene: _Scene) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per object, ``(lo, hi)`` of its parts in its own frame (x along ``frame_yaw``, origin ``frame_pos``): the true
    box, measured before any reconstruction artifact."""
    part_vert_seg = np.concatenate([np.full(len(v), s, dtype=np.int64) for v, _, s in scene.parts])
    house_verts = np.vstack([v for v, _, _ in scene.parts])
    out = []
    for o in scene.objs:
        local = rotate_z(house_verts[np.isin(part_vert_seg, o.segs)] - o.frame_pos, -o.frame_yaw)
        out.append((local.min(axis=0), local.max(axis=0)))
    return out


@dataclass(frozen=True, eq=False)
class _Pose:
    """The house's global pose: house frame -> world frame is a turn by ``yaw`` (radians, about z), then ``offset``
    (metres)."""

    yaw: float
    offset: np.ndarray

    def to_world(self, p) -> np.ndarray:
        """Points ``(..., 3)`` of the house frame as ``(N, 3)`` world points."""
        return rotate_z(np.asarray(p, dtype=np.float64).reshape(-1, 3), self.yaw) + self.offset

    def box_corners(self, lo, hi) -> np.ndarray:
        """The 8 corners ``(8, 3)``, world frame, of the house-frame box ``lo`` .. ``hi``."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        c = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        return self.to_world(c)


def _aabb(p: np.ndarray) -> np.ndarray:
    """``(6,)`` min x y z, max x y z of points ``(N, 3)``."""
    return np.concatenate([p.min(axis=0), p.max(axis=0)])


@dataclass(frozen=True, eq=False)
class _MeshArrays:
    """The scene's parts as one mesh: ``vertices (V, 3)`` world frame, ``faces (F, 3)``, the segment of each face
    (``face_seg (F,)``) and of each vertex (``vert_seg (V,)``), ``areas (F,)`` square metres."""

    vertices: np.ndarray
    faces: np.ndarray
    face_seg: np.ndarray
    vert_seg: np.ndarray
    areas: np.ndarray


def _mesh_arrays(scene: _Scene, pose: _Pose) -> _MeshArrays:
    """Concatenate the scene's parts (house frame) into world-frame mesh arrays."""
    counts = [len(v) for v, _, _ in scene.parts]
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    vertices = pose.to_world(np.vstack([v for v, _, _ in scene.parts]))
    faces = np.vstack([f + o for (_, f, _), o in zip(scene.parts, offsets)]).astype(np.int64)
    face_seg = np.concatenate([np.full(len(f), s, dtype=np.int64) for _, f, s in scene.parts])
    tri = vertices[faces]
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    vert_seg = np.concatenate([np.full(n, s, dtype=np.int64) for n, (_, _, s) in zip(counts, scene.parts)])
    return _MeshArrays(vertices=vertices, faces=faces, face_seg=face_seg, vert_seg=vert_seg, areas=areas)


def _category_records(scene: _Scene) -> tuple[tuple[CategoryRecord, ...], dict[str, int]]:
    """The C records, sorted by category_mapping index (the clutter's rows only when the scene uses them), and the C
    index of each raw name."""
    used_clutter = any(o.raw in _CLUTTER_RAWS for o in scene.objs)
    rows = sorted(CATEGORY_ROWS + (CLUTTER_ROWS if used_clutter else ()))
    c_of_raw = {name: k for k, (_, name, _) in enumerate(rows)}
    return tuple(CategoryRecord(k, idx, name, mp, mpcat40_name(mp)) for k, (idx, name, mp) in enumerate(rows)), c_of_raw


def _segment_ids(scene: _Scene) -> np.ndarray:
    """Each segment's id: region * 1_000_000 + running number in its region (habitat's reading of the ids; opaque to
    the reader)."""
    per_region: dict[int, int] = {}
    seg_ids = np.zeros(len(scene.seg_obj), dtype=np.int64)
    for s, rg in enumerate(scene.seg_region):
        per_region[rg] = per_region.get(rg, 0) + 1
        seg_ids[s] = rg * 1_000_000 + per_region[rg]
    return seg_ids


def _object_records(scene: _Scene, truth: list[tuple[np.ndarray, np.ndarray]], pose: _Pose, c_of_raw: dict[str, int],
                    seg_ids: np.ndarray) -> tuple[list[SynthObject], list[ObjectRecord], list[dict]]:
    """Per object: the ground truth (aligned box from its ``truth`` extents in its own frame, then the world pose),
    its O record and its semseg group."""
    objects, o_recs, groups = [], [], []
    for k, o in enumerate(scene.objs):
        lo, hi = truth[k]
        ext = hi - lo
        centre = rotate_z(((lo + hi) / 2)[None], o.frame_yaw)[0] + o.frame_pos
        yaw = o.frame_yaw if ext[0] >= ext[1] else o.frame_yaw + math.pi / 2
        l, w = max(ext[0], ext[1]), min(ext[0], ext[1])
        yaw_w = float(wrap_angle(yaw + pose.yaw, offset=0.5, period=math.pi))
        c_w = pose.to_world(centre)[0]
        abox = np.array([c_w[0], c_w[1], c_w[2], l, w, ext[2], yaw_w])
        idx, mp = _MAPPING[o.raw]
        objects.append(SynthObject(k, o.region, o.raw, idx, mp, mpcat40_name(mp), o.style, abox))
        center, axes, radii = obb_from_aligned(abox)
        o_recs.append(ObjectRecord(k, o.region, c_of_raw[o.raw], center, axes[0], axes[1], radii))
        groups.append({
            "id": k, "objectId": k, "label": o.raw, "segments": [int(seg_ids[s]) for s in o.segs],
            "obb": {"centroid": [float(v) for v in center], "axesLengths": [float(2 * r) for r in radii],
                    "normalizedAxes": [float(v) for v in axes.ravel()], "dominantNormal": [float(v) for v in axes[2]]},
        })  # fmt: skip
    return objects, o_recs, groups


def _segment_records(mesh: _MeshArrays, seg_obj: np.ndarray, seg_ids: np.ndarray) -> list[SegmentRecord]:
    """The E record of each segment: its object, id, area, centroid and bounding box (world frame)."""
    e_recs = []
    for s in range(len(seg_ids)):
        fm = mesh.face_seg == s
        vm = mesh.vert_seg == s
        pts = mesh.vertices[vm]
        e_recs.append(SegmentRecord(s, int(seg_obj[s]), int(seg_ids[s]), float(mesh.areas[fm].sum()), pts.mean(axis=0),
                                    _aabb(pts)))  # fmt: skip
    return e_recs


def _region_records(rooms: list[_Room], pose: _Pose,
                    ceil_h: float) -> tuple[list[RegionRecord], list[SurfaceRecord], list[VertexRecord]]:
    """Per room: its R record, its floor polygon (S record) and the polygon's corners (V records), world frame."""
    r_recs, s_recs, v_recs = [], [], []
    for room in rooms:
        x0, y0, x1, y1 = room.rect
        corners = pose.box_corners((x0, y0, room.z), (x1, y1, room.z + ceil_h))
        centre = pose.to_world(np.array([(x0 + x1) / 2, (y0 + y1) / 2, room.z]))[0]
        r_recs.append(RegionRecord(room.region, room.level, room.label, centre, _aabb(corners), ceil_h))
        poly = pose.to_world(np.array([[x0, y0, room.z], [x1, y0, room.z], [x1, y1, room.z], [x0, y1, room.z]]))
        s_recs.append(SurfaceRecord(room.region, room.region, 4, "F", centre, np.array([0.0, 0.0, 1.0]), _aabb(poly)))
        for p in poly:
            v_recs.append(VertexRecord(len(v_recs), room.region, "F", p, np.array([0.0, 0.0, 1.0])))
    return r_recs, s_recs, v_recs


def _panorama_records(rooms: list[_Room], pose: _Pose,
                      rng: np.random.Generator) -> tuple[list[PanoramaRecord], list[ImageRecord]]:
    """One panorama per room, near its centre 1.55 m above the floor, with 3 cameras x 2 yaw steps of images."""
    pano_recs, img_recs = [], []
    for room in rooms:
        x0, y0, x1, y1 = room.rect
        pc = pose.to_world(np.array([(x0 + x1) / 2 + rng.uniform(-0.3, 0.3), (y0 + y1) / 2 + rng.uniform(-0.3, 0.3),
                                     room.z + 1.55]))[0]  # fmt: skip
        pano = PanoramaRecord(_hex_id(rng), len(pano_recs), room.region, pc)
        pano_recs.append(pano)
        for cam in range(3):
            for yi in range(2):
                a = pose.yaw + yi * math.pi + cam * 0.4
                pitch = (cam - 1) * math.radians(30)
                # Camera-to-world pose: camera x right, y down, z forward (Matterport convention).
                fwd = np.array([math.cos(a) * math.cos(pitch), math.sin(a) * math.cos(pitch), math.sin(pitch)])
                right = np.array([math.sin(a), -math.cos(a), 0.0])
                down = np.cross(fwd, right)
                ext = np.eye(4)
                ext[:3, 0], ext[:3, 1], ext[:3, 2], ext[:3, 3] = right, down, fwd, pc
                intr = np.array([[1075.5, 0, 629.7], [0, 1075.5, 511.9], [0, 0, 1.0]])
                img_recs.append(ImageRecord(len(img_recs), pano.index, f"{pano.name}_i{cam}_{yi}.jpg", cam, yi, ext,
                                            intr, 1280, 1024, pc))  # fmt: skip
    return pano_recs, img_recs


def _level_records(r_recs: list[RegionRecord], n_levels: int) -> list[LevelRecord]:
    """Per level: its L record, the bounding box of its regions."""
    l_recs = []
    for lv in range(n_levels):
        regs = [r for r in r_recs if r.level == lv]
        bb = np.concatenate([np.min([r.bbox[:3] for r in regs], axis=0), np.max([r.bbox[3:] for r in regs], axis=0)])
        l_recs.append(LevelRecord(lv, len(regs), "-", (bb[:3] + bb[3:]) / 2, bb))
    return l_recs


def _finish(scene: _Scene, layout: _Layout, portals: list[tuple[int, int, np.ndarray]],
            truth: list[tuple[np.ndarray, np.ndarray]], pose: _Pose, rng: np.random.Generator, *, house_id: str,
            seed: int, realism: Realism) -> SyntheticHouse:
    """Turn the scene (its objects' ``truth`` extents measured before the artifacts) into records, world-frame mesh
    arrays with their per-face fields, and ground truth; ``rng`` draws the panoramas."""
    mesh = _mesh_arrays(scene, pose)
    categories, c_of_raw = _category_records(scene)
    seg_ids = _segment_ids(scene)
    material_id = seg_ids[mesh.face_seg]
    seg_obj = np.array(scene.seg_obj, dtype=np.int64)
    face_obj = seg_obj[mesh.face_seg]
    obj_mapping = np.array([_MAPPING[o.raw][0] for o in scene.objs] + [-1], dtype=np.int64)
    segment_id = face_obj.copy()  # O indices equal object positions here
    category_id = obj_mapping[face_obj]
    # Annotation drift: a few faces of one floor carry a wrong category_id (the reader reports the rate).
    floor_obj = next(k for k, o in enumerate(scene.objs) if o.style == "floor")
    drift = np.flatnonzero(face_obj == floor_obj)[:6]
    category_id[drift] = _MAPPING["ceiling"][0]

    objects, o_recs, groups = _object_records(scene, truth, pose, c_of_raw, seg_ids)
    e_recs = _segment_records(mesh, seg_obj, seg_ids)
    r_recs, s_recs, v_recs = _region_records(layout.rooms, pose, layout.grid.ceil_h)
    pano_recs, img_recs = _panorama_records(layout.rooms, pose, rng)
    l_recs = _level_records(r_recs, layout.grid.n_levels)
    p_recs = [PortalRecord(k, a, b, "door", _aabb(pose.box_corners(lohi[0], lohi[1])))
              for k, (a, b, lohi) in enumerate(portals)]  # fmt: skip
    header = HouseHeader(
        name=house_id, label="", n_images=len(img_recs), n_panoramas=len(pano_recs), n_vertices=len(v_recs),
        n_surfaces=len(s_recs), n_segments=len(e_recs), n_objects=len(o_recs), n_categories=len(categories),
        n_regions=len(r_recs), n_portals=len(p_recs), n_levels=len(l_recs), bbox=_aabb(mesh.vertices),
    )  # fmt: skip
    hf = HouseFile(
        version="1.1", header=header, levels=tuple(l_recs), regions=tuple(r_recs), portals=tuple(p_recs),
        surfaces=tuple(s_recs), vertices=tuple(v_recs), panoramas=tuple(pano_recs), images=tuple(img_recs),
        categories=categories, objects=tuple(o_recs), segments=tuple(e_recs),
    )  # fmt: skip
    palette = np.array([mpcat40_color(_MAPPING[o.raw][1]) for o in scene.objs] + [(128, 128, 128)], dtype=np.uint8)
    return SyntheticHouse(
        id=house_id, seed=seed, house_file=hf, vertices=mesh.vertices, faces=mesh.faces, material_id=material_id,
        segment_id=segment_id, category_id=category_id, colors=palette[seg_obj[mesh.vert_seg]],
        objects=tuple(objects), seg_groups=tuple(groups), n_levels=layout.grid.n_levels, global_yaw=pose.yaw,
        global_offset=pose.offset, mismatched_faces=len(drift), unlabelled_faces=int(np.count_nonzero(face_obj < 0)),
        realism=realism,
    )  # fmt: skip


# ------------------------------------------------------------------------------------------------ writing


def house_seed(seed: int, k: int) -> int:
    """The seed of house ``k`` of a set generated with ``seed`` (independent streams per house)."""
    return int(np.random.SeedSequence([int(seed), int(k)]).generate_state(1, dtype=np.uint64)[0] >> 1)


def plan_houses(n: int, seed: int) -> list[tuple[str, int, int]]:
    """``(id, house seed, levels)`` of the ``n`` houses of a set: house 0 has two levels, house 1 one, the rest
    random; ids are unique 11-character strings."""
    out, seen = [], set()
    for k in range(n):
        hs = house_seed(seed, k)
        rng = np.random.default_rng([hs, 1])
        hid = make_house_id(rng)
        while hid in seen:
            hid = make_house_id(rng)
        seen.add(hid)
        levels = 2 if k == 0 else 1 if k == 1 else int(rng.integers(1, 3))
        out.append((hid, hs, levels))
    return out


#: Where the habitat layout keeps a house (``mp3d/<id>/`` inside ``mp3d_habitat.zip`` and once extracted).
HABITAT_ZIP = "mp3d_habitat.zip"


def _zip_bytes(members: dict[str, bytes]) -> bytes:
    """A zip of ``{member name: bytes}`` as the download script fetches it (fixed timestamps: deterministic bytes)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, data in members.items():
            info = zipfile.ZipInfo(name, date_time=(2017, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, data, compresslevel=6)
    return buf.getvalue()


def _habitat_members(house: SyntheticHouse) -> dict[str, bytes]:
    return {f"mp3d/{house.id}/{house.id}{suffix}": data for suffix, data in house.habitat_files().items()}


def write_house(out_root: str | Path, house: SyntheticHouse, zip_files: bool = False,
                layout: str = "release") -> Path:
    """Write one house under ``out_root``: release layout ``v1/scans/<id>/`` (extracted ``house_segmentations/`` or
    the zip), habitat layout ``mp3d/<id>/`` (or ``mp3d_habitat.zip`` holding just this house)."""
    if layout == "habitat":
        if zip_files:
            with atomic_open(Path(out_root) / HABITAT_ZIP, "wb") as f:
                f.write(_zip_bytes(_habitat_members(house)))
            return Path(out_root) / HABITAT_ZIP
        for name, data in _habitat_members(house).items():
            write_bytes(Path(out_root) / name, data)
        return Path(out_root) / "mp3d" / house.id
    if layout != "release":
        raise ValueError(f"layout must be 'release' or 'habitat', got {layout!r}")
    scan = Path(out_root) / "v1" / "scans" / house.id
    files = house.files()
    if zip_files:
        with atomic_open(scan / "house_segmentations.zip", "wb") as f:
            f.write(_zip_bytes({f"{house.id}/house_segmentations/{house.id}{k}": v for k, v in files.items()}))
        return scan / "house_segmentations.zip"
    folder = scan / "house_segmentations"
    for suffix, data in files.items():
        write_bytes(folder / f"{house.id}{suffix}", data)
    return folder


def subdivide_house(house: SyntheticHouse, times: int) -> SyntheticHouse:
    """``house`` with every triangle split into 4 (edge midpoints), ``times`` times: the same surfaces, objects and
    labels with 4**times as many faces.

    Real Matterport3D house meshes have ~0.5-3 M faces, the procedural ones a few thousand; subdivided houses make
    raycasting and reading cost what they cost on real data (benchmarks), at identical geometry. Per-face fields are
    copied to the 4 children in order (face ``f`` becomes ``4 f .. 4 f + 3``), vertex colours are averaged.
    """
    import trimesh.remesh

    if times < 0:
        raise ValueError("times must be >= 0")
    v, f = house.vertices, house.faces
    colors = house.colors.astype(np.float64)
    per_face = [house.material_id, house.segment_id, house.category_id]
    for _ in range(times):
        # Subdividing every face, trimesh emits old face i's four children as faces 4 i .. 4 i + 3 (its
        # ``return_index`` map says so too, but is not returned together with vertex attributes).
        v, f, attrs = trimesh.remesh.subdivide(v, f, vertex_attributes={"c": colors})
        colors = attrs["c"]
        per_face = [np.repeat(a, 4) for a in per_face]
    return SyntheticHouse(
        id=house.id, seed=house.seed, house_file=house.house_file, vertices=np.asarray(v, dtype=np.float64),
        faces=np.asarray(f, dtype=house.faces.dtype), material_id=per_face[0], segment_id=per_face[1],
        category_id=per_face[2], colors=np.rint(colors).astype(house.colors.dtype), objects=house.objects,
        seg_groups=house.seg_groups, n_levels=house.n_levels, global_yaw=house.global_yaw,
        global_offset=house.global_offset, mismatched_faces=house.mismatched_faces * 4**times,
        unlabelled_faces=house.unlabelled_faces * 4**times, realism=house.realism,
    )


def write_synthetic_houses(
    out_root: str | Path, n: int, seed: int, zip_files: bool = False, progress=None, subdivide: int = 0,
    layout: str = "release", realism: Realism = DEFAULT,
) -> list[str]:
    """Write ``n`` synthetic houses (seeded by ``seed``) under ``out_root`` in the download ``layout`` (``release``:
    ``v1/scans/<id>/...``; ``habitat``: ``mp3d/<id>/...``, with ``zip_files`` one ``mp3d_habitat.zip`` for all);
    return their ids. ``progress`` is an optional callable invoked once per house (e.g. a tqdm ``update``);
    ``subdivide`` splits every triangle into 4 that many times (:func:`subdivide_house`); ``realism`` sets the
    reconstruction artifacts and clutter (:mod:`mpchair.synth.realism`).
    """
    ids = []
    members: dict[str, bytes] = {}
    for hid, hs, levels in plan_houses(n, seed):
        house = subdivide_house(synthesize_house(hs, hid, levels=levels, realism=realism), subdivide)
        if layout == "habitat" and zip_files:
            members.update(_habitat_members(house))
        else:
            write_house(out_root, house, zip_files=zip_files, layout=layout)
        ids.append(hid)
        if progress is not None:
            progress(1)
    if members:
        with atomic_open(Path(out_root) / HABITAT_ZIP, "wb") as f:
            f.write(_zip_bytes(members))
    return ids
