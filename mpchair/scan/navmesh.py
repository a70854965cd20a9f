"""The walkable surface of a habitat navmesh: islands, habitat's island radius, area-weighted points, snapping.

What habitat-sim's ``PathFinder`` offers for viewpoints, rebuilt over :class:`mpchair.matterport.navmesh.NavMesh`
arrays (world frame: Matterport, z up, metres):

- **usable polygons**: walkable (``POLY_WALK``), not disabled, ground polygons with a positive area (habitat's query
  filter; it disables zero-area polygons at load);
- **islands**: connected components of usable polygons over shared edges; an island's **radius** is habitat's
  ``island_radius``: the largest distance from the mean of its polygons' corners (each corner of each polygon
  counted) to any of those corners;
- **sampling** (:class:`NavmeshSampler`): Detour's ``findRandomPoint`` picks a polygon by its horizontal area and a
  uniform point in it; here a detail triangle is picked by horizontal area and a uniform point in it, which is the same
  distribution over the surface. habitat-lab's PointNav generator rejected start points on islands of radius
  < 1.5 m (``ISLAND_RADIUS_LIMIT``), so only islands at least that large are sampled;
- **snapping** (:func:`snap_points`): the nearest point of the usable surface.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from mpchair.matterport.navmesh import POLY_DISABLED, POLY_WALK, NavMesh

#: habitat-lab PointNav's ``ISLAND_RADIUS_LIMIT`` (metres): episodes start only on islands at least this large.
ISLAND_RADIUS_MIN = 1.5


def _tri_areas(tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T,) surface areas and (T,) horizontal (xy-projected) areas of (T,3,3) triangles, square metres."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    cross = np.cross(e1, e2)
    return 0.5 * np.linalg.norm(cross, axis=1), 0.5 * np.abs(cross[:, 2])


def usable_polygons(nav: NavMesh) -> np.ndarray:
    """(P,) bool: walkable, not disabled, ground polygons with a positive area (habitat's filter)."""
    area = np.zeros(len(nav.poly_flags))
    np.add.at(area, nav.triangle_poly, _tri_areas(nav.triangles)[0])
    flags = nav.poly_flags.astype(np.int64)
    return ((flags & POLY_WALK) != 0) & ((flags & POLY_DISABLED) == 0) & (nav.poly_type == 0) & (area > 0)


def island_labels(nav: NavMesh) -> np.ndarray:
    """(P,) int64 island of every polygon (connected components of usable polygons over shared edges), numbered
    0.. in order of their first polygon; -1 for unusable polygons."""
    ok = usable_polygons(nav)
    n = len(ok)
    links = nav.links[ok[nav.links[:, 0]] & ok[nav.links[:, 1]]] if len(nav.links) else nav.links
    graph = coo_matrix((np.ones(len(links)), (links[:, 0], links[:, 1])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    labels = np.full(n, -1, dtype=np.int64)
    # Renumber components of usable polygons by first appearance, so island ids do not depend on scipy's numbering.
    _, first, inverse = np.unique(comp[ok], return_index=True, return_inverse=True)
    order = np.argsort(np.argsort(first))
    labels[ok] = order[inverse.ravel()]
    return labels


def island_radii(nav: NavMesh, labels: np.ndarray) -> np.ndarray:
    """(K,) habitat's island radius (metres) of each island of ``labels`` (see the module docstring)."""
    k = int(labels.max()) + 1 if len(labels) and labels.max() >= 0 else 0
    used = (np.arange(nav.poly_vertices.shape[1])[None, :] < nav.poly_vert_count[:, None]) & (labels >= 0)[:, None]
    poly, slot = np.nonzero(used)
    pts = nav.vertices[nav.poly_vertices[poly, slot]]
    isl = labels[poly]
    centre = np.zeros((k, 3))
    np.add.at(centre, isl, pts)
    centre /= np.maximum(np.bincount(isl, minlength=k), 1)[:, None]
    radius = np.zeros(k)
    np.maximum.at(radius, isl, np.linalg.norm(pts - centre[isl], axis=1))
    return radius


class NavmeshSampler:
    """Uniform (area-weighted) points on the islands of a navmesh whose radius is at least ``min_island_radius``
    (world frame); built once per house. ``island_radius (K,)`` and ``island_area (K,)`` (horizontal, m²) describe
    every island, ``islands`` lists the sampled ones."""

    def __init__(self, nav: NavMesh, min_island_radius: float = ISLAND_RADIUS_MIN):
        labels = island_labels(nav)
        self.island_radius = island_radii(nav, labels)
        tri_island = labels[nav.triangle_poly] if len(nav.triangle_poly) else np.zeros(0, np.int64)
        _, flat = _tri_areas(nav.triangles)
        self.island_area = np.bincount(tri_island[tri_island >= 0], weights=flat[tri_island >= 0],
                                       minlength=len(self.island_radius))  # fmt: skip
        self.islands = np.flatnonzero(self.island_radius >= min_island_radius)
        keep = np.isin(tri_island, self.islands) & (flat > 0)
        if not keep.any():
            big = float(self.island_radius.max()) if len(self.island_radius) else 0.0
            raise ValueError(f"no navmesh island has a radius of at least {min_island_radius} m (largest: {big:.2f} m)")
        self._tri = nav.triangles[keep]
        self._tri_island = tri_island[keep]
        w = flat[keep]
        self._cum = np.cumsum(w / w.sum())

    def sample(self, rng: np.random.Generator) -> tuple[int, float, float, float]:
        """One ``(island, x, y, z)``: a triangle drawn by horizontal area, then a uniform point in it."""
        t = min(int(np.searchsorted(self._cum, rng.random(), side="right")), len(self._cum) - 1)
        u, v = rng.random(2)
        if u + v > 1.0:  # fold the square onto the triangle: uniform over it
            u, v = 1.0 - u, 1.0 - v
        a, b, c = self._tri[t]
        p = a + u * (b - a) + v * (c - a)
        return int(self._tri_island[t]), float(p[0]), float(p[1]), float(p[2])


def closest_on_triangles(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(T,3) closest point to ``p (3,)`` on each of the (T,3,3) triangles (Ericson, *Real-Time Collision Detection*
    5.1.5, vectorised over triangles)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp, cp = p - b, p - c
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v_in, w_in = vb / denom, vc / denom
        out = a + ab * v_in[:, None] + ac * w_in[:, None]  # inside the face
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    # Regions, checked from the last to the first so the first matching one wins (as in the scalar version).
    cases = [
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + (c - b) * t_bc[:, None]),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * t_ac[:, None]),
        ((d6 >= 0) & (d5 <= d6), c),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * t_ab[:, None]),
        ((d3 >= 0) & (d4 <= d3), b),
        ((d1 <= 0) & (d2 <= 0), a),
    ]
    for mask, value in cases:
        out = np.where(mask[:, None], value, out)
    return out


def snap_points(nav: NavMesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest point of the usable walkable surface to each of ``points (N,3)`` (world frame, metres): returns the
    snapped ``(N,3)`` points and the ``(N,)`` detail triangle each lies on (index into ``nav.triangles``)."""
    ok = usable_polygons(nav)[nav.triangle_poly]
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        raise ValueError("the navmesh has no usable polygon")
    tri = nav.triangles[idx]
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out, which = np.empty_like(pts), np.empty(len(pts), dtype=np.int64)
    for i, p in enumerate(pts):
        q = closest_on_triangles(p, tri)
        d = np.einsum("ij,ij->i", q - p, q - p)
        j = int(np.argmin(np.where(np.isnan(d), np.inf, d)))  # degenerate triangles give nan: never nearest
        out[i], which[i] = q[j], idx[j]
    return out, which
