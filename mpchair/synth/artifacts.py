"""Reconstruction artifacts applied to a built synthetic scene (house frame, metres): the surface and label knobs of
:class:`~mpchair.synth.realism.Realism`.

:func:`apply_artifacts` takes the scene's parts after every object's true box has been measured (``truth``) and
returns the parts the mesh is written from; it appends the segments it creates (label bleed, ghosts, unlabelled
parts) to the scene's segment lists. Order matters for the seeded stream, so it is fixed: re-mesh, surface holes,
mirror holes, floor under tables, object artifacts, fragments, then noise and waves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely

from mpchair.synth.primitives import cbox, rotate_z
from mpchair.synth.realism import (
    Realism,
    bleed_rects,
    box_extent,
    face_centres,
    face_normals,
    floor_tiles,
    grid_box,
    in_discs,
    keep_in_box,
    vertex_noise,
    wave_field,
)

#: Object styles that are the house's shell: re-meshed as grids, warped by waves, holed; their boxes may warp.
STRUCTURE = ("wall", "floor", "ceiling")
CHAIR = 3  # mpcat40 index
THIN = 0.05  # m: a chair part thinner than this is a leg, post or stretcher


@dataclass
class Part:
    """One mesh part on its way to the file: house-frame ``v`` (n,3), ``f`` (m,3), segment ``seg``; ``truth``:
    part of the object's real geometry (kept inside the object's box), not an artifact."""

    v: np.ndarray
    f: np.ndarray
    seg: int
    truth: bool = True


def _areas(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    t = v[f]
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)


def _drop(part: Part, drop: np.ndarray) -> None:
    """Remove the faces marked in ``drop`` unless that would leave the part empty (segments keep a face)."""
    if drop.any() and not drop.all():
        part.f = part.f[~drop]


def _new_segment(scene, obj: int, region: int) -> int:
    s = len(scene.seg_obj)
    scene.seg_obj.append(obj)
    scene.seg_region.append(region)
    if obj >= 0:
        scene.objs[obj].segs.append(s)
    return s


def _surface_holes(parts: list[Part], style, realism: Realism, rng: np.random.Generator) -> None:
    """Glossy and dark patches: discs of missing faces on walls, floors and ceilings (``surface_holes`` per 10 m²)."""
    shell = [p for p in parts if style(p.seg) in STRUCTURE]
    if not shell or realism.surface_holes <= 0:
        return
    cent = np.vstack([face_centres(p.v, p.f) for p in shell])
    area = np.concatenate([_areas(p.v, p.f) for p in shell])
    n = int(rng.poisson(realism.surface_holes * area.sum() / 2 / 10.0))  # both sides of every slab
    if n == 0:
        return
    pick = rng.choice(len(cent), size=n, p=area / area.sum())
    discs = np.column_stack([cent[pick], rng.uniform(*realism.hole_radius, n)])
    gone = in_discs(cent, discs)
    start = 0
    for p in shell:
        m = len(p.f)
        _drop(p, gone[start : start + m])
        start += m


def _cut_boxes(parts: list[Part], style, kinds: tuple[str, ...], boxes: list[tuple[np.ndarray, np.ndarray]]) -> None:
    """Remove the faces of ``kinds`` parts whose centres lie in any of the axis-aligned ``boxes`` (lo, hi)."""
    if not boxes:
        return
    for p in parts:
        if style(p.seg) in kinds:
            c = face_centres(p.v, p.f)
            _drop(p, np.any([np.all((c >= lo) & (c <= hi), axis=1) for lo, hi in boxes], axis=0))


def _mirror_boxes(rooms, realism: Realism, rng: np.random.Generator, wall_t: float) -> list:
    """Mirror-sized through-holes in a wall of bathrooms and bedrooms (mirrors reconstruct as holes)."""
    out = []
    for room in rooms:
        if room.label not in ("a", "b") or rng.random() >= realism.mirror_holes:
            continue
        x0, y0, x1, y1 = room.rect
        side = int(rng.integers(4))
        w, h, z0 = rng.uniform(0.5, 0.9), rng.uniform(0.6, 1.0), room.z + rng.uniform(0.9, 1.2)
        reach = wall_t + 0.02  # through the wall, from the room's side
        if side in (0, 2):
            u = rng.uniform(x0 + w / 2 + 0.1, x1 - w / 2 - 0.1)
            y = y0 - reach if side == 0 else y1
            lo, hi = (u - w / 2, y, z0), (u + w / 2, y + reach, z0 + h)
        else:
            u = rng.uniform(y0 + w / 2 + 0.1, y1 - w / 2 - 0.1)
            x = x1 if side == 1 else x0 - reach
            lo, hi = (x, u - w / 2, z0), (x + reach, u + w / 2, z0 + h)
        out.append((np.array(lo) - 0.005, np.array(hi) + 0.005))
    return out


def _floor_under_tables(parts: list[Part], scene, style, truth, realism: Realism, rng, slab: float) -> None:
    """The floor under a table (its footprint less 0.1 m) is missing: the camera never saw it."""
    for k, o in enumerate(scene.objs):
        if o.style != "table" or rng.random() >= realism.floor_under_tables:
            continue
        lo, hi = truth[k]
        c = np.array([[lo[0] + 0.1, lo[1] + 0.1, 0], [hi[0] - 0.1, lo[1] + 0.1, 0], [hi[0] - 0.1, hi[1] - 0.1, 0],
                      [lo[0] + 0.1, hi[1] - 0.1, 0]])  # fmt: skip
        if hi[0] - lo[0] < 0.3 or hi[1] - lo[1] < 0.3:
            continue
        poly = shapely.Polygon(rotate_z(c, o.frame_yaw)[:, :2] + o.frame_pos[:2])
        z = o.frame_pos[2]
        for p in parts:
            if style(p.seg) == "floor":
                cen = face_centres(p.v, p.f)
                level = (cen[:, 2] > z - slab - 0.01) & (cen[:, 2] < z + 0.01)
                _drop(p, level & shapely.contains_xy(poly, cen[:, 0], cen[:, 1]))


def _chair_hole(scene, k: int, room, truth, realism: Realism, rng: np.random.Generator, parts: list[Part]) -> None:
    """A see-through hole in chair ``k``'s biggest part, and its label bleeding onto the floor around it."""
    o = scene.objs[k]
    mine = [p for p in parts if p.truth and p.seg in o.segs]
    big = max(mine, key=lambda p: float(_areas(p.v, p.f).sum()))
    drop = np.zeros(len(big.f), dtype=bool)
    drop[rng.choice(len(big.f), size=min(len(big.f) - 1, int(rng.integers(2, 5))), replace=False)] = True
    _drop(big, drop)
    lo, hi = truth[k]
    widths = rng.uniform(*realism.bleed_width, 4) * (rng.random(4) < 0.75)
    tv, tf = floor_tiles(bleed_rects(lo, hi, widths), lo[2] + 0.025)
    if len(tf) == 0:
        return
    tv = rotate_z(tv, o.frame_yaw) + o.frame_pos
    # Only tiles on this room's floor: a label does not bleed through a wall.
    x0, y0, x1, y1 = room.rect
    quad = tv.reshape(-1, 4, 3)
    ok = np.all((quad[:, :, 0] > x0 + 0.01) & (quad[:, :, 0] < x1 - 0.01) & (quad[:, :, 1] > y0 + 0.01)
                & (quad[:, :, 1] < y1 - 0.01), axis=1)  # fmt: skip
    if not ok.any():
        return
    keep = np.repeat(ok, 2)
    parts.append(Part(tv, tf[keep], _new_segment(scene, k, o.region), truth=False))


def _ghost(scene, k: int, room, truth, realism: Realism, rng: np.random.Generator, parts: list[Part]) -> None:
    """A small floating fragment ``ghost_distance`` beside chair ``k``'s box carrying its label (a split object: a
    piece mis-registered from another scan). Near the chair: the label filters' dense regions grow with the distance."""
    o = scene.objs[k]
    lo, hi = truth[k]
    ang = rng.uniform(0, 2 * math.pi)
    s = rng.uniform(0.08, 0.3, 3)
    reach = float(np.hypot(*(hi[:2] - lo[:2]))) / 2 + s.max() / 2 + rng.uniform(*realism.ghost_distance)
    local = np.array([(lo[0] + hi[0]) / 2 + reach * math.cos(ang), (lo[1] + hi[1]) / 2 + reach * math.sin(ang),
                      rng.uniform(0.2, 1.6)])  # fmt: skip
    c = rotate_z(local[None], o.frame_yaw)[0] + o.frame_pos
    x0, y0, x1, y1 = room.rect
    c[:2] = np.clip(c[:2], [x0 + 0.2, y0 + 0.2], [x1 - 0.2, y1 - 0.2])  # inside the chair's room, not through a wall
    parts.append(Part(*cbox(*c, *s), _new_segment(scene, k, o.region), truth=False))


def _object_artifacts(parts: list[Part], scene, rooms, truth, realism: Realism, rng: np.random.Generator) -> None:
    """Per object: thin chair parts with holes, open undersides, one part unlabelled, chair holes and ghosts."""
    room_of = {r.region: r for r in rooms}
    by_seg: dict[int, list[Part]] = {}
    for p in parts:
        by_seg.setdefault(p.seg, []).append(p)
    for k, o in enumerate(scene.objs):
        if o.style in STRUCTURE or o.style in ("window", "stairs", "railing", "rail"):
            continue
        mine = [p for s in o.segs for p in by_seg.get(s, [])]
        chair = o.mpcat40 == CHAIR
        for p in mine:
            ext = np.ptp(p.v, axis=0)
            if chair and min(ext[0], ext[1]) < THIN and rng.random() < realism.thin_part_holes:
                drop = np.zeros(len(p.f), dtype=bool)
                drop[rng.choice(len(p.f), size=min(len(p.f) - 1, int(rng.integers(2, 5))), replace=False)] = True
                _drop(p, drop)
            if box_extent(p.v, p.f) is not None and rng.random() < realism.open_undersides:
                _drop(p, face_normals(p.v, p.f)[:, 2] < -0.9)
        if len(mine) > 1 and rng.random() < realism.unlabelled_parts:
            p = mine[int(rng.integers(len(mine)))]
            if sum(q.seg == p.seg for q in mine) > 1:  # its segment keeps other parts (no empty E record)
                p.seg = _new_segment(scene, -1, o.region)
        if chair and o.region in room_of:
            if rng.random() < realism.chair_holes:
                _chair_hole(scene, k, room_of[o.region], truth, realism, rng, parts)
            if rng.random() < realism.chair_ghosts:
                _ghost(scene, k, room_of[o.region], truth, realism, rng, parts)


def _fragments(parts: list[Part], scene, rooms, realism: Realism, rng: np.random.Generator) -> None:
    """Small floating unlabelled fragments (``fragments`` per room on average)."""
    for room in rooms:
        for _ in range(int(rng.poisson(realism.fragments))):
            x0, y0, x1, y1 = room.rect
            c = np.array([rng.uniform(x0 + 0.2, x1 - 0.2), rng.uniform(y0 + 0.2, y1 - 0.2),
                          room.z + rng.uniform(0.2, 2.4)])  # fmt: skip
            parts.append(Part(*cbox(*c, *rng.uniform(0.03, 0.2, 3)), _new_segment(scene, -1, room.region), False))


def _noise_and_waves(parts: list[Part], scene, style, truth, realism: Realism, rng: np.random.Generator) -> None:
    """Scanner noise on every vertex and slow waves on the shell; objects' real parts stay in their true boxes."""
    if not parts:
        return
    sizes = [len(p.v) for p in parts]
    allv = np.vstack([p.v for p in parts])
    shell = np.concatenate([np.full(n, style(p.seg) in STRUCTURE) for n, p in zip(sizes, parts)])
    phases = rng.uniform(0, 2 * math.pi, (3, 2))
    moved = allv + vertex_noise(allv, realism.vertex_noise, rng)
    moved[shell] += wave_field(allv[shell], realism.wave_amplitude, realism.wave_length, phases)
    start = 0
    for n, p in zip(sizes, parts):
        v = moved[start : start + n]
        obj = scene.seg_obj[p.seg]
        if p.truth and obj >= 0 and style(p.seg) not in STRUCTURE:
            o = scene.objs[obj]
            v = keep_in_box(v, *truth[obj], o.frame_yaw, o.frame_pos)
        p.v = v
        start += n


def apply_artifacts(scene, rooms, truth: list, realism: Realism, rng: np.random.Generator, *, wall_t: float,
                    slab: float) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """The scene's parts as ``[(vertices, faces, segment)]`` with ``realism``'s artifacts (module docstring).

    ``scene``: the house's ``_Scene`` (``parts``, ``seg_obj``, ``seg_region``, ``objs`` with ``style``, ``mpcat40``,
    ``segs``, ``frame_yaw``, ``frame_pos``, ``region``); ``rooms``: its rooms (``rect``, ``z``, ``label``,
    ``region``); ``truth[k]``: object ``k``'s true box as (lo, hi) in its own frame. ``wall_t`` / ``slab``: wall and
    slab thickness (m).
    """

    def style(seg: int) -> str:
        obj = scene.seg_obj[seg]
        return scene.objs[obj].style if obj >= 0 else "junk"

    parts = [Part(v, f, s) for v, f, s in scene.parts]
    if realism.remesh:
        for p in parts:
            ext = box_extent(p.v, p.f) if style(p.seg) in STRUCTURE else None
            if ext is not None:
                p.v, p.f = grid_box(*ext, realism.cell)
    _surface_holes(parts, style, realism, rng)
    _cut_boxes(parts, style, ("wall",), _mirror_boxes(rooms, realism, rng, wall_t))
    _floor_under_tables(parts, scene, style, truth, realism, rng, slab)
    _object_artifacts(parts, scene, rooms, truth, realism, rng)
    _fragments(parts, scene, rooms, realism, rng)
    _noise_and_waves(parts, scene, style, truth, realism, rng)
    return [(p.v, p.f, p.seg) for p in parts]
