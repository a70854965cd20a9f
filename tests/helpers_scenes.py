"""Small hand-made :class:`House` objects for the scan / labels / generate tests (world frame, z up, metres).

A room is a floor slab, four walls and a ceiling (closed boxes); chairs are closed boxes labelled mpcat40 ``chair``
whose aligned box is exactly their mesh's extent, so boxes converted through a pose can be checked exactly.
"""

from __future__ import annotations

import numpy as np
import trimesh

from mpchair.matterport.house import House, HouseObject, Level, Region

FLOOR, WALL, CHAIR, TABLE, CEILING = 2, 1, 3, 5, 17
NAMES = {FLOOR: "floor", WALL: "wall", CHAIR: "chair", TABLE: "table", CEILING: "ceiling"}


def box_mesh(center, size, yaw: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A closed box mesh: ``size`` (l, w, h) along (heading, across, up), centred at ``center``, rotated by yaw."""
    m = trimesh.creation.box(extents=size)
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    return m.vertices @ R.T + np.asarray(center, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)


class HouseBuilder:
    """Collect parts (mesh + optional object), then :meth:`build` a :class:`House` (optionally offset in xy/z)."""

    def __init__(self, house_id: str = "TESTHOUSE01"):
        self.id = house_id
        self.parts: list[tuple[np.ndarray, np.ndarray, int, np.ndarray | None]] = []
        self.regions: list[tuple[np.ndarray, float, str]] = []

    def add(self, vertices, faces, category: int = -1, box=None) -> int:
        """Add a mesh part; ``category`` >= 0 makes it an object (``box`` (7,) world aligned box). Returns its index."""
        self.parts.append((np.asarray(vertices, float), np.asarray(faces, np.int64), category,
                           None if box is None else np.asarray(box, float)))
        return len(self.parts) - 1

    def add_box(self, center, size, yaw: float = 0.0, category: int = -1) -> int:
        v, f = box_mesh(center, size, yaw)
        box = np.array([*center, *size, yaw], dtype=float) if category >= 0 else None
        return self.add(v, f, category, box)

    def room(self, x0: float, y0: float, x1: float, y1: float, height: float = 2.6, label: str = "d",
             wall: float = 0.1, doors: bool = False) -> None:
        """A room with floor (top at z = 0), walls and ceiling; its floor polygon becomes a region."""
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        self.add_box((cx, cy, -0.05), (x1 - x0 + 2 * wall, y1 - y0 + 2 * wall, 0.1), category=FLOOR)
        self.add_box((cx, cy, height + 0.05), (x1 - x0 + 2 * wall, y1 - y0 + 2 * wall, 0.1), category=CEILING)
        self.add_box((x0 - wall / 2, cy, height / 2), (wall, y1 - y0, height), category=WALL)
        self.add_box((x1 + wall / 2, cy, height / 2), (wall, y1 - y0, height), category=WALL)
        self.add_box((cx, y0 - wall / 2, height / 2), (x1 - x0, wall, height), category=WALL)
        self.add_box((cx, y1 + wall / 2, height / 2), (x1 - x0, wall, height), category=WALL)
        self.regions.append((np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float), 0.0, label))

    def chair(self, x: float, y: float, yaw: float = 0.0, size=(0.5, 0.45, 0.9)) -> int:
        """A box chair standing on the floor (z = 0); returns the object's position in ``House.objects``."""
        self.add_box((x, y, size[2] / 2), size, yaw, category=CHAIR)
        return sum(1 for p in self.parts if p[2] >= 0) - 1

    def build(self, offset=(0.0, 0.0, 0.0)) -> House:
        off = np.asarray(offset, dtype=np.float64)
        verts, faces, fobj, fcat, objects = [], [], [], [], []
        nv = 0
        for v, f, cat, box in self.parts:
            verts.append(v + off)
            faces.append(f + nv)
            nv += len(v)
            if cat >= 0:
                k = len(objects)
                b = box.copy()
                b[:3] += off
                l, w, h, yaw = b[3:]
                c, s = np.cos(yaw), np.sin(yaw)
                axes = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
                objects.append(HouseObject(
                    index=k, id=f"0_0_{k}", region=0, raw_category=NAMES[cat], category_index=cat,
                    mapping_index=cat, mpcat40_index=cat, mpcat40_name=NAMES[cat], center=b[:3].copy(), axes=axes,
                    radii=np.array([l, w, h]) / 2, aligned_box=b, tilt_deg=0.0))
                fobj.append(np.full(len(f), k))
                fcat.append(np.full(len(f), cat))
            else:
                fobj.append(np.full(len(f), -1))
                fcat.append(np.full(len(f), -1))
        V = np.vstack(verts)
        regions = tuple(
            Region(index=i, level=0, label=lab, label_name="room", floor_polygon=poly + off[:2], floor_z=z + off[2],
                   height=2.6, position=np.array([*poly.mean(axis=0), z]) + off, bbox=np.zeros(6))
            for i, (poly, z, lab) in enumerate(self.regions))
        fo = np.concatenate(fobj).astype(np.int64)
        return House(
            id=self.id, version="1.1", vertices=V, faces=np.vstack(faces), face_object=fo,
            face_category=np.concatenate(fcat).astype(np.int64), face_segment=fo.copy(), objects=tuple(objects),
            regions=regions, levels=(Level(0, "-", tuple(range(len(regions))), np.zeros(3), np.zeros(6)),),
            categories=(), portals=(), panoramas=(), images=(), seg_groups=(),
            bbox=np.concatenate([V.min(axis=0), V.max(axis=0)]), label_mismatch_rate=0.0, warnings=())
