"""Robot viewpoints on free floor: sample a candidate spot, drop onto the floor by a ray, check clearance.

Candidates come from a :class:`PointSampler`: :class:`FloorSampler` (``--viewpoints regions``: uniform inside the
``.house`` region floor polygons) or :class:`mpchair.scan.navmesh.NavmeshSampler` (``--viewpoints navmesh``: uniform
on habitat's navmesh islands of radius >= 1.5 m, as habitat-lab's PointNav generator). Either way the checks below
decide.

Everything here is in the world frame (Matterport, z up, metres). A viewpoint is a sensor pose: position
``(x, y, floor_z + height)`` and a yaw (radians, CCW about +z, uniform in [0, 2 pi)); no pitch or roll.

Validity of a candidate ``(x, y)`` in a floor area at height ``z_floor``:

1. **drop**: a ray straight down from ``z_floor + drop_start`` must hit a face allowed as floor (``floor_ok``) within
   ``drop_tolerance`` of ``z_floor``, whose normal points up. Landing on a seat or a bed fails here;
2. **headroom**: a ray straight up from just above the floor must not hit anything below ``height + head_margin``
   (nothing over the robot: tables, shelves, the inside of closed furniture);
3. **clearance**: at each of ``clearance_heights`` (metres above the floor, up to the sensor) ``clearance_rays``
   horizontal rays must travel at least ``robot_radius`` before hitting anything (walls, furniture legs).

Viewpoint streams are pure functions of their generator: the same ``numpy.random.Generator`` state gives the same
sequence of viewpoints, whatever else runs.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Sequence
from typing import Protocol

import numpy as np
import shapely

from mpchair.scan.raycast import Raycaster


@dataclasses.dataclass(frozen=True)
class FloorArea:
    """A horizontal floor polygon (world frame): ``polygon`` (K,2) x/y metres, floor height ``z`` (metres),
    and where it comes from (``level`` index, ``region`` index, or -1)."""

    polygon: np.ndarray
    z: float
    level: int = -1
    region: int = -1


@dataclasses.dataclass(frozen=True)
class ViewpointParams:
    """How viewpoints are sampled and validated (metres unless noted).

    ``height``: sensor above the floor (1.0 = the paper; 1.25 = the original code). ``robot_radius``: nothing closer
    horizontally (0.25). ``clearance_heights``: fractions of ``height`` at which clearance is checked (sensor height
    included). ``clearance_rays``: horizontal directions per height. ``drop_start``: the drop ray starts this far above
    the area's floor height; ``drop_tolerance``: the floor hit must be this close to it. ``head_margin``: headroom
    above the sensor. ``min_floor_normal_z``: the floor face's normal must be this close to +z. ``batch``: candidates
    tested per raycast batch (no effect on results).
    """

    height: float = 1.0
    robot_radius: float = 0.25
    clearance_heights: tuple[float, ...] = (0.1, 0.5, 1.0)
    clearance_rays: int = 16
    drop_start: float = 0.5
    drop_tolerance: float = 0.2
    head_margin: float = 0.1
    min_floor_normal_z: float = 0.9
    batch: int = 8

    def __post_init__(self) -> None:
        if self.height <= 0 or self.robot_radius < 0:
            raise ValueError("height must be > 0 and robot_radius >= 0 (metres)")
        if self.clearance_rays < 1 or self.batch < 1:
            raise ValueError("clearance_rays and batch must be >= 1")


@dataclasses.dataclass(frozen=True)
class Viewpoint:
    """A sensor pose in the world frame: ``position`` (3,) metres (the sensor, ``height`` above ``floor_z``), ``yaw``
    radians in [0, 2 pi), the ``area`` index it was sampled in, and ``attempt`` (0-based candidate number)."""

    position: np.ndarray
    yaw: float
    floor_z: float
    area: int
    attempt: int

    def pose(self) -> np.ndarray:
        """(4,4) sensor → world transform ``T_world_from_sensor`` (rotation about z by ``yaw``)."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        T = np.eye(4)
        T[:2, :2] = [[c, -s], [s, c]]
        T[:3, 3] = self.position
        return T


class PointSampler(Protocol):
    """Draws viewpoint candidates: ``sample(rng) -> (area index, x, y, floor z)`` (world frame, metres)."""

    def sample(self, rng: np.random.Generator) -> tuple[int, float, float, float]: ...


class FloorSampler:
    """Uniform (area-weighted) points inside a set of floor areas; built once per house."""

    def __init__(self, areas: Sequence[FloorArea]):
        self.areas = tuple(areas)
        polys = [shapely.Polygon(np.asarray(a.polygon, dtype=np.float64)) for a in self.areas]
        polys = [p if p.is_valid else p.buffer(0) for p in polys]  # self-touching annotator polygons
        self._polys = polys
        area = np.array([p.area for p in polys], dtype=np.float64)
        self._keep = np.flatnonzero(area > 1e-6)
        if len(self._keep) == 0:
            raise ValueError("no floor area with a positive area")
        w = area[self._keep]
        self._cum = np.cumsum(w / w.sum())
        self._bounds = np.array([p.bounds for p in polys])
        for p in polys:
            shapely.prepare(p)

    def sample(self, rng: np.random.Generator) -> tuple[int, float, float, float]:
        """One ``(area index, x, y, z)``; x, y uniform inside the chosen area's polygon (rejection in its bbox), z the
        area's floor height."""
        k = int(self._keep[min(int(np.searchsorted(self._cum, rng.random(), side="right")), len(self._keep) - 1)])
        x0, y0, x1, y1 = self._bounds[k]
        poly = self._polys[k]
        while True:  # ends: the polygon has positive area inside its own bounding box
            xy = rng.random((32, 2))
            x = x0 + xy[:, 0] * (x1 - x0)
            y = y0 + xy[:, 1] * (y1 - y0)
            inside = np.flatnonzero(shapely.contains_xy(poly, x, y))
            if len(inside):
                return k, float(x[inside[0]]), float(y[inside[0]]), float(self.areas[k].z)


def validate_candidates(
    xy: np.ndarray,
    floor_z: np.ndarray,
    raycaster: Raycaster,
    floor_ok: np.ndarray,
    face_normal_z: np.ndarray,
    params: ViewpointParams,
) -> tuple[np.ndarray, np.ndarray]:
    """Check B candidates (see the module docstring); returns ``(valid (B,) bool, floor height (B,) metres)``.

    ``xy`` (B,2) and ``floor_z`` (B,) world frame; ``floor_ok`` (F,) bool marks faces a robot may stand on;
    ``face_normal_z`` (F,) the z component of each face's unit normal (sign-free: |n_z| is used).
    """
    B = len(xy)
    # 1. drop onto the floor
    o = np.column_stack([xy, floor_z + params.drop_start])
    d = np.tile([0.0, 0.0, -1.0], (B, 1))
    t, face = raycaster.cast(o, d)
    hit = face >= 0
    fz = o[:, 2] - t
    ok = hit & (np.abs(fz - floor_z) <= params.drop_tolerance)
    fsafe = np.where(hit, face, 0)
    ok &= floor_ok[fsafe] & (np.abs(face_normal_z[fsafe]) >= params.min_floor_normal_z)
    fz = np.where(ok, fz, floor_z)
    # 2. headroom, 3. clearance: one batch of rays for all candidates
    eps = 0.02  # start just above the floor surface so the floor itself is not hit
    up_o = np.column_stack([xy, fz + eps])
    ang = 2.0 * np.pi * np.arange(params.clearance_rays) / params.clearance_rays
    dirs = np.column_stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)])
    hs = np.asarray(params.clearance_heights, dtype=np.float64) * params.height
    H, K = len(hs), len(dirs)
    co = np.empty((B, H, K, 3))
    co[..., 0] = xy[:, 0, None, None]
    co[..., 1] = xy[:, 1, None, None]
    co[..., 2] = fz[:, None, None] + np.maximum(hs, eps)[None, :, None]
    cd = np.broadcast_to(dirs[None, None], (B, H, K, 3))
    all_o = np.vstack([up_o, co.reshape(-1, 3)])
    all_d = np.vstack([np.tile([0.0, 0.0, 1.0], (B, 1)), cd.reshape(-1, 3)])
    t2, _ = raycaster.cast(all_o, all_d)
    ok &= t2[:B] >= params.height + params.head_margin - eps
    ok &= (t2[B:].reshape(B, H * K) >= params.robot_radius).all(axis=1)
    return ok, fz


def viewpoint_stream(
    rng: np.random.Generator,
    sampler: PointSampler,
    raycaster: Raycaster,
    floor_ok: np.ndarray,
    face_normal_z: np.ndarray,
    params: ViewpointParams,
    max_attempts: int,
) -> Iterator[Viewpoint]:
    """Valid viewpoints in candidate order, drawn from ``rng``, until ``max_attempts`` candidates were tried.

    Each candidate draws ``(area, x, y, z)`` then a yaw from ``rng``, so the stream is a pure function of the
    generator's state (batching only groups the raycasts). ``Viewpoint.attempt`` counts candidates from 0.
    """
    attempt = 0
    while attempt < max_attempts:
        n = min(params.batch, max_attempts - attempt)
        cand, yaws = [], np.empty(n)
        for i in range(n):  # spot, then yaw, candidate by candidate: the batch size cannot change the stream
            cand.append(sampler.sample(rng))
            yaws[i] = rng.random() * 2.0 * np.pi
        xy = np.array([[c[1], c[2]] for c in cand])
        z = np.array([c[3] for c in cand])
        valid, fz = validate_candidates(xy, z, raycaster, floor_ok, face_normal_z, params)
        for i in range(n):
            if valid[i]:
                pos = np.array([xy[i, 0], xy[i, 1], fz[i] + params.height])
                yield Viewpoint(position=pos, yaw=float(yaws[i]), floor_z=float(fz[i]), area=cand[i][0],
                                attempt=attempt + i)
        attempt += n


def face_normals_z(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) z component of each face's unit normal (world frame); 0 for degenerate faces."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    norm = np.linalg.norm(n, axis=1)
    return np.where(norm > 0, n[:, 2] / np.where(norm > 0, norm, 1.0), 0.0)
