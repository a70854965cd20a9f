"""Closed triangle-mesh primitives for synthetic houses: boxes, oriented bars and cylinders (metres, z up).

Every primitive returns ``(vertices (n,3) float64, faces (m,3) int64)`` with outward-facing counter-clockwise
triangles, so each part is a closed surface that a ray caster sees from every side.
"""

from __future__ import annotations

import math

import numpy as np

# Unit cube corners (0/1 per axis) and its 12 outward CCW triangles.
_CUBE = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=np.float64)
_CUBE_FACES = np.array(
    [
        [0, 2, 1], [1, 2, 3],  # bottom (z = 0), normal -z
        [4, 5, 6], [5, 7, 6],  # top (z = 1), normal +z
        [0, 1, 4], [1, 5, 4],  # y = 0, normal -y
        [2, 6, 3], [3, 6, 7],  # y = 1, normal +y
        [0, 4, 2], [2, 4, 6],  # x = 0, normal -x
        [1, 3, 5], [3, 7, 5],  # x = 1, normal +x
    ],
    dtype=np.int64,
)  # fmt: skip

Mesh = tuple[np.ndarray, np.ndarray]


def box(lo, hi) -> Mesh:
    """Axis-aligned box from corner ``lo`` (3,) to ``hi`` (3,): 8 vertices, 12 triangles."""
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    return lo + _CUBE * (hi - lo), _CUBE_FACES.copy()


def cbox(cx: float, cy: float, cz: float, sx: float, sy: float, sz: float) -> Mesh:
    """Axis-aligned box by centre (cx, cy, cz) and full sizes (sx, sy, sz)."""
    c = np.array([cx, cy, cz])
    h = np.array([sx, sy, sz]) / 2
    return box(c - h, c + h)


def bar(p0, p1, width: float, thickness: float, side=(0.0, 1.0, 0.0)) -> Mesh:
    """A box of square-ish section running from point ``p0`` to ``p1``; ``width`` is measured along ``side``
    (made orthogonal to the bar), ``thickness`` along the third direction."""
    p0 = np.asarray(p0, dtype=np.float64)
    p1 = np.asarray(p1, dtype=np.float64)
    u = p1 - p0
    u /= np.linalg.norm(u)
    v = np.asarray(side, dtype=np.float64) - np.dot(side, u) * u
    if np.linalg.norm(v) < 1e-9:
        v = np.cross(u, [0.0, 0.0, 1.0]) if abs(u[2]) < 0.9 else np.cross(u, [1.0, 0.0, 0.0])
    v /= np.linalg.norm(v)
    n = np.cross(u, v)
    length = float(np.linalg.norm(p1 - p0))
    # Map the unit cube: x → along the bar, y → width, z → thickness (right-handed, so faces stay outward).
    corners = _CUBE.copy()
    verts = (
        p0
        + np.outer(corners[:, 0] * length, u)
        + np.outer((corners[:, 1] - 0.5) * width, v)
        + np.outer((corners[:, 2] - 0.5) * thickness, n)
    )
    return verts, _CUBE_FACES.copy()


def cylinder(cx: float, cy: float, z0: float, z1: float, radius: float, segments: int = 10) -> Mesh:
    """Closed vertical cylinder (a ``segments``-gon prism) with axis at (cx, cy) from z0 to z1."""
    a = np.arange(segments) * (2 * math.pi / segments)
    ring = np.stack([cx + radius * np.cos(a), cy + radius * np.sin(a)], axis=1)
    bottom = np.column_stack([ring, np.full(segments, z0)])
    top = np.column_stack([ring, np.full(segments, z1)])
    verts = np.vstack([bottom, top, [[cx, cy, z0], [cx, cy, z1]]])
    k = np.arange(segments)
    k1 = (k + 1) % segments
    cb, ct = 2 * segments, 2 * segments + 1
    faces = np.concatenate(
        [
            np.stack([k, k1, segments + k1], axis=1),
            np.stack([k, segments + k1, segments + k], axis=1),
            np.stack([np.full(segments, cb), k1, k], axis=1),
            np.stack([np.full(segments, ct), segments + k, segments + k1], axis=1),
        ]
    )
    return verts, faces.astype(np.int64)


def rotate_z(verts: np.ndarray, yaw: float, origin=(0.0, 0.0)) -> np.ndarray:
    """Rotate (n,3) points by ``yaw`` radians CCW about the vertical axis through ``origin`` (x, y)."""
    c, s = math.cos(yaw), math.sin(yaw)
    o = np.array([origin[0], origin[1], 0.0])
    p = verts - o
    out = np.empty_like(p)
    out[:, 0] = c * p[:, 0] - s * p[:, 1]
    out[:, 1] = s * p[:, 0] + c * p[:, 1]
    out[:, 2] = p[:, 2]
    return out + o


def rect_minus_rect(outer: tuple[float, float, float, float], hole: tuple[float, float, float, float]) -> list:
    """Split rectangle ``outer`` (x0, y0, x1, y1) minus ``hole`` into up to four rectangles (same format)."""
    x0, y0, x1, y1 = outer
    hx0, hy0, hx1, hy1 = max(hole[0], x0), max(hole[1], y0), min(hole[2], x1), min(hole[3], y1)
    if hx0 >= hx1 or hy0 >= hy1:
        return [outer]
    out = []
    if hy0 > y0:
        out.append((x0, y0, x1, hy0))
    if hy1 < y1:
        out.append((x0, hy1, x1, y1))
    if hx0 > x0:
        out.append((x0, hy0, hx0, hy1))
    if hx1 < x1:
        out.append((hx1, hy0, x1, hy1))
    return out
