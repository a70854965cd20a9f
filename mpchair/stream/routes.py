"""Episode routes through free space: a start and a goal on one level, and a collision-free path between them.

Sampling (habitat-lab's PointNav rules, seeded): a start cell uniform over the free cells of islands whose radius is at
least ``min_island_radius``; a goal uniform over the cells of the same island whose geodesic distance from the start
lies in ``[min_geodesic, max_geodesic]`` and whose geodesic / Euclidean ratio is at least ``min_ratio``; a start
without such a goal is redrawn. Geodesic distances are shortest paths on the 8-connected grid (a diagonal step needs
both side cells free).

Path: the cheapest grid path where each step costs its length times ``1 + clearance_weight * max(0, 1 - c /
clearance_scale)`` (``c`` the distance to the nearest non-free cell, metres), so the path keeps away from walls where
it can; Dijkstra finds the same optimum as A*. Then line-of-sight shortcutting: from each waypoint, the path goes
straight to the farthest following cell the straight segment reaches through free cells only.

World frame (Matterport, z up, metres).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np
from scipy import ndimage
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from mpchair.stream.freespace import FreeSpace

#: Neighbour offsets (row, col) of each undirected grid edge, listed once.
_STEPS = ((0, 1), (1, 0), (1, 1), (1, -1))


@dataclasses.dataclass(frozen=True)
class RouteRules:
    """How routes are drawn (metres): the protocol's habitat-lab rules and the path's clearance preference."""

    min_geodesic: float = 5.0
    max_geodesic: float = 30.0
    min_ratio: float = 1.1
    min_island_radius: float = 1.5
    clearance_scale: float = 0.5
    clearance_weight: float = 3.0

    def __post_init__(self) -> None:
        if not 0 <= self.min_geodesic <= self.max_geodesic:
            raise ValueError("need 0 <= min_geodesic <= max_geodesic (metres)")
        if self.min_ratio < 1.0:
            raise ValueError("min_ratio (geodesic / Euclidean) must be >= 1")
        if self.min_island_radius < 0 or self.clearance_scale <= 0 or self.clearance_weight < 0:
            raise ValueError("min_island_radius >= 0, clearance_scale > 0 and clearance_weight >= 0 are needed")


@dataclasses.dataclass(frozen=True, eq=False)
class Route:
    """A start → goal route on one level: ``waypoints`` (K,2) world x, y (first = start, last = goal; K = 1 for a
    robot that stays put), ``geodesic`` and ``euclidean`` start → goal distances (metres)."""

    level: int
    waypoints: np.ndarray
    geodesic: float
    euclidean: float

    @property
    def length(self) -> float:
        """Length of the shortcut path (metres)."""
        return float(np.linalg.norm(np.diff(self.waypoints, axis=0), axis=1).sum())


def _edges(space: FreeSpace) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(a, b, length)`` of every undirected edge between free cells (flat indices, metres)."""
    free = space.free
    h, w = free.shape
    a_all, b_all, l_all = [], [], []
    for dr, dc in _STEPS:
        r0, r1 = 0, h - dr
        c0, c1 = max(0, -dc), w - max(0, dc)
        src = free[r0:r1, c0:c1]
        dst = free[r0 + dr : r1 + dr, c0 + dc : c1 + dc]
        ok = src & dst
        if dr and dc:  # no corner cutting: both side cells must be free too
            ok &= free[r0 + dr : r1 + dr, c0:c1] & free[r0:r1, c0 + dc : c1 + dc]
        rr, cc = np.nonzero(ok)
        rr, cc = rr + r0, cc + c0
        a_all.append(rr * w + cc)
        b_all.append((rr + dr) * w + cc + dc)
        l_all.append(np.full(len(rr), space.cell * math.hypot(dr, dc)))
    return np.concatenate(a_all), np.concatenate(b_all), np.concatenate(l_all)


def _graph(n: int, a: np.ndarray, b: np.ndarray, weight: np.ndarray) -> csr_matrix:
    """Symmetric sparse graph over ``n`` nodes with edges ``a — b`` of positive ``weight``."""
    return csr_matrix((np.concatenate([weight, weight]), (np.concatenate([a, b]), np.concatenate([b, a]))),
                      shape=(n, n))


def clearance(space: FreeSpace) -> np.ndarray:
    """(H, W) distance (metres) from each cell centre to the nearest non-free cell centre (0 on non-free cells)."""
    return ndimage.distance_transform_edt(space.free) * space.cell


def segment_free(space: FreeSpace, a: np.ndarray, b: np.ndarray) -> bool:
    """Whether the straight segment between world points ``a`` and ``b`` passes through free cells only (sampled
    every half cell)."""
    n = int(math.ceil(float(np.linalg.norm(np.asarray(b) - np.asarray(a))) / (space.cell / 2))) + 1
    t = np.linspace(0.0, 1.0, n)[:, None]
    return bool(space.is_free(np.asarray(a) * (1 - t) + np.asarray(b) * t).all())


def shortcut(space: FreeSpace, points: np.ndarray) -> np.ndarray:
    """Line-of-sight shortcutting of a grid path ``points`` (K,2) world x, y: keep a point only where the straight
    segment from the previous kept point to the next one would leave free space."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) <= 2:
        return points.copy()
    out = [points[0]]
    anchor = 0
    j = 1
    while j < len(points) - 1:
        if not segment_free(space, points[anchor], points[j + 1]):
            out.append(points[j])
            anchor = j
        j += 1
    out.append(points[-1])
    return np.array(out)


def grid_path(space: FreeSpace, start: int, goal: int, rules: RouteRules) -> np.ndarray:
    """(K,2) world x, y of the cheapest grid path (clearance-weighted, see the module docstring) from flat cell
    ``start`` to flat cell ``goal`` of the same island."""
    a, b, length = _edges(space)
    c = clearance(space).reshape(-1)
    mean_c = (c[a] + c[b]) / 2
    cost = length * (1.0 + rules.clearance_weight * np.maximum(0.0, 1.0 - mean_c / rules.clearance_scale))
    _, pred = dijkstra(_graph(space.free.size, a, b, cost), indices=start, return_predecessors=True)
    cells = [goal]
    while cells[-1] != start:
        cells.append(int(pred[cells[-1]]))
        if cells[-1] < 0:
            raise ValueError("goal not reachable from start")
    w = space.free.shape[1]
    rc = np.array([[i // w, i % w] for i in reversed(cells)])
    return space.centres_of(rc)


def sample_start(rng: np.random.Generator, spaces: Sequence[FreeSpace], rules: RouteRules) -> tuple[int, int]:
    """``(space index, flat cell)`` uniform over the free cells of islands with radius >= ``min_island_radius``."""
    pools = [np.flatnonzero((s.island_radius >= rules.min_island_radius)[s.islands.reshape(-1)]
                            & s.free.reshape(-1)) for s in spaces]
    sizes = np.array([len(p) for p in pools])
    if sizes.sum() == 0:
        raise ValueError(f"no free island with a radius of at least {rules.min_island_radius} m")
    k = int(rng.integers(int(sizes.sum())))
    li = int(np.searchsorted(np.cumsum(sizes), k, side="right"))
    return li, int(pools[li][k - int(sizes[:li].sum())])


def sample_route(rng: np.random.Generator, spaces: Sequence[FreeSpace], rules: RouteRules, tries: int = 100) -> Route:
    """A route drawn with ``rng`` by the rules of the module docstring; ``ValueError`` after ``tries`` starts without
    a valid goal."""
    for _ in range(tries):
        li, start = sample_start(rng, spaces, rules)
        space = spaces[li]
        a, b, length = _edges(space)
        geo = dijkstra(_graph(space.free.size, a, b, length), indices=start)
        w = space.free.shape[1]
        cells = np.arange(space.free.size)
        euclid = np.hypot(cells // w - start // w, cells % w - start % w) * space.cell
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = geo / euclid
        ok = ((geo >= rules.min_geodesic) & (geo <= rules.max_geodesic) & np.isfinite(geo) & (euclid > 0)
              & (ratio >= rules.min_ratio))
        goals = np.flatnonzero(ok)
        if len(goals) == 0:
            continue
        goal = int(goals[rng.integers(len(goals))])
        path = shortcut(space, grid_path(space, start, goal, rules))
        return Route(level=space.level, waypoints=path, geodesic=float(geo[goal]), euclidean=float(euclid[goal]))
    raise ValueError(f"no start/goal pair found in {tries} starts (geodesic {rules.min_geodesic}-{rules.max_geodesic} "
                     f"m, geodesic/Euclidean >= {rules.min_ratio})")


def standing_route(rng: np.random.Generator, spaces: Sequence[FreeSpace], rules: RouteRules) -> Route:
    """A route of one point (a robot that does not translate): a start cell drawn as by :func:`sample_route`."""
    li, start = sample_start(rng, spaces, rules)
    w = spaces[li].free.shape[1]
    xy = spaces[li].centres_of(np.array([[start // w, start % w]]))
    return Route(level=spaces[li].level, waypoints=xy, geodesic=0.0, euclidean=0.0)
