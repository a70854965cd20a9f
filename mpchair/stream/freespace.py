"""Where a robot can stand: a 5 cm grid per house level, each cell checked like a ``generate`` viewpoint.

A level's floor polygons (:func:`mpchair.dataset.frame.floor_areas`, grouped by ``FloorArea.level``), or a habitat
navmesh's walkable triangles grouped by island (:func:`navmesh_areas`), are rasterised at ``cell`` metres; every cell
centre inside one of them is validated with :func:`mpchair.scan.viewpoints.validate_candidates` (drop onto a floor
face, headroom, ``robot_radius`` clearance at several heights), so free space is exactly the set of places
``generate`` could put its sensor. Free cells form *islands* (8-connected components); an island's radius is the
largest distance of its cells from their centroid (habitat-sim's island radius, on the grid).

World frame (Matterport, z up, metres). Grid cell ``(row, col)`` has its centre at ``origin + (col, row) * cell``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import shapely
from scipy import ndimage

from mpchair.matterport.navmesh import NavMesh
from mpchair.scan.navmesh import island_labels
from mpchair.scan.raycast import Raycaster
from mpchair.scan.viewpoints import FloorArea, ViewpointParams, validate_candidates

#: Grid resolution (metres): the protocol's 5 cm.
CELL = 0.05
#: Candidates validated per raycast batch (memory only; no effect on the result).
BATCH = 4096


@dataclasses.dataclass(frozen=True, eq=False)
class FreeSpace:
    """The free cells of one level (world frame).

    ``origin`` (2,) x, y of cell (0, 0)'s centre; ``cell`` metres; ``free`` (H, W) bool (row = y, column = x);
    ``floor_z`` (H, W) floor height under each free cell (NaN elsewhere); ``islands`` (H, W) int32 island id of each
    free cell (0 = not free); ``island_radius`` (n + 1,) metres per island id (index 0 unused).
    """

    level: int
    origin: np.ndarray
    cell: float
    free: np.ndarray
    floor_z: np.ndarray
    islands: np.ndarray
    island_radius: np.ndarray

    def cells_of(self, xy: np.ndarray) -> np.ndarray:
        """(N,2) int64 ``[row, col]`` of the cells nearest to world points ``xy`` (N,2) (may lie off the grid)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        return np.round((xy[:, ::-1] - self.origin[::-1]) / self.cell).astype(np.int64)

    def centres_of(self, rc: np.ndarray) -> np.ndarray:
        """(N,2) world x, y of cells ``rc`` (N,2) ``[row, col]``."""
        rc = np.asarray(rc, dtype=np.float64).reshape(-1, 2)
        return self.origin + rc[:, ::-1] * self.cell

    def is_free(self, xy: np.ndarray) -> np.ndarray:
        """(N,) bool: the cell nearest to each world point ``xy`` (N,2) is free (off the grid: not free)."""
        rc = self.cells_of(xy)
        h, w = self.free.shape
        on = (rc[:, 0] >= 0) & (rc[:, 0] < h) & (rc[:, 1] >= 0) & (rc[:, 1] < w)
        out = np.zeros(len(rc), dtype=bool)
        out[on] = self.free[rc[on, 0], rc[on, 1]]
        return out

    def floor_at(self, xy: np.ndarray) -> np.ndarray:
        """(N,) floor height (metres) of the cell nearest to each world point ``xy`` (N,2); the points must be free."""
        rc = self.cells_of(xy)
        return self.floor_z[rc[:, 0], rc[:, 1]]


def _level_grid(polygons: list[tuple[shapely.Polygon, float]], cell: float) -> tuple[np.ndarray, np.ndarray]:
    """``(origin (2,), z (H, W))``: the floor height of the first polygon containing each cell centre (NaN: none).
    Each polygon is tested only on the cells of its own bounding box."""
    bounds = np.array([p.bounds for p, _ in polygons])
    lo = np.floor(bounds[:, :2].min(axis=0) / cell) * cell
    hi = bounds[:, 2:].max(axis=0)
    w, h = (np.floor((hi - lo) / cell).astype(np.int64) + 1).tolist()
    z = np.full((h, w), np.nan)
    for (poly, pz), (x0, y0, x1, y1) in zip(polygons, bounds):
        c0, r0 = np.ceil((np.array([x0, y0]) - lo) / cell - 1e-9).astype(np.int64)
        c1, r1 = np.floor((np.array([x1, y1]) - lo) / cell + 1e-9).astype(np.int64)
        if c1 < c0 or r1 < r0:
            continue
        gx, gy = np.meshgrid(lo[0] + np.arange(c0, c1 + 1) * cell, lo[1] + np.arange(r0, r1 + 1) * cell)
        window = z[r0 : r1 + 1, c0 : c1 + 1]
        todo = np.isnan(window)
        inside = np.zeros_like(todo)
        inside[todo] = shapely.contains_xy(poly, gx[todo], gy[todo])
        window[inside] = pz
    return lo, z


def _island_radii(islands: np.ndarray, n: int, cell: float) -> np.ndarray:
    """(n + 1,) max distance (metres) of each island's cells from their centroid."""
    rows, cols = np.nonzero(islands)
    ids = islands[rows, cols]
    count = np.bincount(ids, minlength=n + 1).astype(np.float64)
    cr = np.bincount(ids, rows, minlength=n + 1) / np.maximum(count, 1)
    cc = np.bincount(ids, cols, minlength=n + 1) / np.maximum(count, 1)
    d = np.hypot(rows - cr[ids], cols - cc[ids]) * cell
    out = np.zeros(n + 1)
    np.maximum.at(out, ids, d)
    return out


def navmesh_areas(nav: NavMesh) -> list[FloorArea]:
    """The walkable surface of a habitat navmesh as floor areas: one triangle each (x, y, mean z), grouped by island
    (``FloorArea.level`` = island id, so each island gets its own grid); unusable polygons are left out."""
    islands = island_labels(nav)
    tri_island = islands[nav.triangle_poly]
    return [FloorArea(t[:, :2].copy(), float(t[:, 2].mean()), int(k)) for t, k in zip(nav.triangles, tri_island)
            if k >= 0]


def free_space(
    areas: Sequence[FloorArea],
    raycaster: Raycaster,
    floor_ok: np.ndarray,
    face_normal_z: np.ndarray,
    params: ViewpointParams,
    cell: float = CELL,
) -> list[FreeSpace]:
    """One :class:`FreeSpace` per level of ``areas`` (levels in ascending order; levels without a free cell are left
    out). ``raycaster``, ``floor_ok`` and ``face_normal_z`` are the house's (see
    :func:`~mpchair.scan.viewpoints.validate_candidates`); ``params`` give the sensor height and robot radius."""
    out = []
    for level in sorted({a.level for a in areas}):
        polys = []
        for a in areas:
            if a.level != level:
                continue
            p = shapely.Polygon(np.asarray(a.polygon, dtype=np.float64))
            p = p if p.is_valid else p.buffer(0)  # self-touching annotator polygons
            if p.area > 1e-6:
                shapely.prepare(p)
                polys.append((p, float(a.z)))
        if not polys:
            continue
        origin, z = _level_grid(polys, cell)
        h, w = z.shape
        idx = np.flatnonzero(~np.isnan(z))
        free = np.zeros(h * w, dtype=bool)
        floor_z = np.full(h * w, np.nan)
        for s in range(0, len(idx), BATCH):
            part = idx[s : s + BATCH]
            xy = np.column_stack([origin[0] + (part % w) * cell, origin[1] + (part // w) * cell])
            ok, fz = validate_candidates(xy, z.flat[part], raycaster, floor_ok, face_normal_z, params)
            free[part] = ok
            floor_z[part[ok]] = fz[ok]
        free = free.reshape(h, w)
        if not free.any():
            continue
        islands, n = ndimage.label(free, structure=np.ones((3, 3), dtype=bool))
        out.append(FreeSpace(level=int(level), origin=origin, cell=float(cell), free=free,
                             floor_z=floor_z.reshape(h, w), islands=islands.astype(np.int32),
                             island_radius=_island_radii(islands, n, cell)))
    return out
