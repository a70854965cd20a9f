"""A habitat navmesh for a synthetic house, built from its floor the way Recast would see it (world frame, metres).

Recast voxelises the scene and keeps floor where an agent of height ``agent_height`` fits, steps of at most
``max_climb`` and ``agent_radius`` away from obstacles. The synthetic houses are made of closed convex parts (boxes,
prisms), so the same rules fit in a few polygon operations:

1. **floor**: the upward faces of ``floor`` objects, grouped by height (one group per level, :func:`_levels_of`; the
   stair opening is a hole in the upper floor);
2. **obstacles**: every connected part of the mesh that reaches into ``(floor + max_climb, floor + agent_height)``
   blocks its convex footprint (walls beside doors, furniture, stair steps; door lintels and ceilings do not);
3. **walkable** = floor − obstacles, eroded by ``agent_radius``; constrained-Delaunay triangles of it become the
   navmesh polygons (one tile, :func:`mpchair.matterport.navmesh.encode_navmesh`).

Pockets cut off by furniture become small islands, as in real navmeshes. Used only to write test and demo data in
habitat's layout (``mpchair synth --layout habitat``).
"""

from __future__ import annotations

import numpy as np
import shapely
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from mpchair.matterport.navmesh import DEFAULT_SETTINGS


def _levels_of(face_z: np.ndarray, gap: float = 0.3) -> np.ndarray:
    """(F,) level number of each upward floor face: heights sorted and split where they jump by more than ``gap`` m
    (a level's floor is flat up to the realism model's noise and waves, levels are ~3 m apart)."""
    if len(face_z) == 0:
        return np.zeros(0, dtype=np.int64)
    order = np.argsort(face_z, kind="stable")
    level_sorted = np.concatenate([[0], np.cumsum(np.diff(face_z[order]) > gap)])
    out = np.empty(len(face_z), dtype=np.int64)
    out[order] = level_sorted
    return out


def walkable_polygons(
    vertices: np.ndarray,
    faces: np.ndarray,
    floor_faces: np.ndarray,
    *,
    agent_height: float = DEFAULT_SETTINGS["agent_height"],
    agent_radius: float = DEFAULT_SETTINGS["agent_radius"],
    max_climb: float = DEFAULT_SETTINGS["agent_max_climb"],
) -> list[tuple[float, shapely.Geometry]]:
    """``[(floor height, walkable area)]`` per level (module docstring); ``vertices (V,3)`` world frame, ``faces
    (F,3)``, ``floor_faces (F,)`` bool marks the faces of floor objects."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    up = floor_faces & (n[:, 2] > 0.9 * np.linalg.norm(n, axis=1))
    face_z = tri[up, :, 2].mean(axis=1)
    heights = _levels_of(face_z)

    # Connected parts of the mesh (faces sharing vertices), with their height range and xy points.
    graph = coo_matrix((np.ones(2 * len(f)), (np.r_[f[:, 0], f[:, 1]], np.r_[f[:, 1], f[:, 2]])),
                       shape=(len(v), len(v)))  # fmt: skip
    _, part = connected_components(graph, directed=False)
    order = np.argsort(part, kind="stable")
    bounds = np.flatnonzero(np.diff(part[order])) + 1
    groups = np.split(order, bounds)
    zlo = np.array([v[g, 2].min() for g in groups])
    zhi = np.array([v[g, 2].max() for g in groups])

    out = []
    for level in np.unique(heights):
        z = float(np.mean(face_z[heights == level]))
        floor = shapely.union_all([shapely.Polygon(t[:, :2]) for t in tri[up][heights == level]])
        hit = np.flatnonzero((zlo < z + agent_height) & (zhi > z + max_climb))
        blocks = [shapely.MultiPoint(v[groups[k], :2]).convex_hull for k in hit]
        free = floor.difference(shapely.union_all(blocks)) if blocks else floor
        free = free.buffer(-agent_radius, join_style="mitre")
        if not free.is_empty:
            out.append((z, free))
    return out


def navmesh_polygons(levels: list[tuple[float, shapely.Geometry]]) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of the walkable areas as navmesh input: ``vertices (V,3)`` (world frame, each level at its floor
    height) and ``polys (P,3)`` vertex indices, shared vertices merged so neighbouring triangles link."""
    tris = []
    for z, area in levels:
        for t in shapely.get_parts(shapely.constrained_delaunay_triangles(area)):
            ring = np.asarray(t.exterior.coords)[:3]
            a = 0.5 * ((ring[1, 0] - ring[0, 0]) * (ring[2, 1] - ring[0, 1])
                       - (ring[2, 0] - ring[0, 0]) * (ring[1, 1] - ring[0, 1]))  # fmt: skip
            if abs(a) < 1e-9:
                continue
            if a < 0:
                ring = ring[::-1]
            tris.append(np.column_stack([ring, np.full(3, z)]))
    if not tris:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    corners = np.concatenate(tris)
    vertices, index = np.unique(corners, axis=0, return_inverse=True)
    return vertices, index.reshape(-1, 3).astype(np.int64)
