"""First-hit raycasting of a triangle mesh behind one protocol, with two backends that give the same hits.

``cast(origins, directions) -> (t, face_id)``: origins (N,3), or (3,) shared by all rays, and directions (N,3) in the
mesh's frame (the world
frame, Matterport z up, metres; directions need not be unit); ``t`` (N,) float64 is the ray parameter of the first hit
(``hit = origin + t * direction``, so metres when directions are unit vectors, planar depth for ``(1, ., .)``
directions), ``inf`` on a miss; ``face_id`` (N,) int64 indexes the mesh's faces, -1 on a miss.

Precision: both backends work in float32. Matterport houses sit at an arbitrary global offset, so every scene is
built on a *recentred* copy of the mesh (vertices minus their bounding-box centre, in float64, then float32) and rays
are recentred the same way before the cast; float32 then resolves ~1e-6 of a house's size instead of ~1e-6 of its
offset. The Embree backend further recomputes ``t`` from the hit face's plane in float64.

The scene is built once per mesh and reused for every frame. Open3D is imported only when its backend is used.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from mpchair.errors import InputError

#: Ray-triangle cosines below this count as grazing when recomputing ``t`` from the face plane (then the backend's
#: float32 hit position is used instead, since the plane equation is ill-conditioned there).
_GRAZING_COS = 1e-6


class Raycaster(Protocol):
    """A first-hit ray caster over one triangle mesh (see the module docstring for frames and units)."""

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(t (N,) float64, inf on miss; face_id (N,) int64, -1 on miss) of the first hit of each ray."""
        ...

    def first_faces(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """face_id (N,) int64 of the first hit (-1 on miss) only: the same faces as :meth:`cast`, cheaper."""
        ...


def _check_mesh(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"expected vertices (V,3) and faces (F,3), got {v.shape} and {f.shape}")
    if len(f) == 0:
        raise ValueError("cannot raycast a mesh without faces")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError("face indices out of range")
    return v, f


def _check_rays(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,3) or (1,3) float64 origins (a (3,) origin is shared by all rays) and (N,3) float64 directions."""
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    if len(o) != 1 and o.shape != d.shape:
        raise ValueError(f"origins {o.shape} and directions {d.shape} differ")
    return o, d


class EmbreeRaycaster:
    """Embree (Intel) through embreex, the engine behind trimesh's ``ray_pyembree.RayMeshIntersector``; the default.

    The embreex scene is built directly (as trimesh's ``_EmbreeWrap`` does) rather than through
    ``RayMeshIntersector.intersects_first``, which copies and re-normalises every direction array: that overhead
    alone was about as large as the raycast itself for our ray counts. Embree returns the first hit's face id and its
    float32 ``tfar``; ``t`` is then solved in float64 on that face's plane (kept from ``tfar`` only at grazing angles,
    where the plane equation is ill-conditioned).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        v, f = _check_mesh(vertices, faces)
        self.centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
        self._v = v - self.centre
        self._scene = rtcore_scene.EmbreeScene()
        TriangleMesh(scene=self._scene, vertices=self._v.astype(np.float32), indices=f.astype(np.int32))
        a, b, c = self._v[f[:, 0]], self._v[f[:, 1]], self._v[f[:, 2]]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n, axis=1)
        self._normal = n / np.where(norm > 0, norm, 1.0)[:, None]  # unit normals (degenerate faces: zero)
        self._offset = np.einsum("ij,ij->i", self._normal, a)  # plane: n . x = offset

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """See :class:`Raycaster`."""
        o, d = _check_rays(origins, directions)
        n = len(d)
        t = np.full(n, np.inf)
        if n == 0:
            return t, np.zeros(0, dtype=np.int64)
        oc = o - self.centre
        shared = o.shape[0] == 1  # one origin for all rays (a sensor): no per-ray origin gathers below
        o32 = np.empty((n, 3), dtype=np.float32)
        o32[:] = oc.astype(np.float32)
        face = self._scene.run(o32, np.ascontiguousarray(d, dtype=np.float32)).astype(np.int64)
        hit = np.flatnonzero(face >= 0)
        if len(hit):
            fh = face[hit]
            nrm = self._normal[fh]
            dh = d[hit]
            denom = np.einsum("ij,ij->i", nrm, dh)
            # (no BLAS matvec for the shared origin: its threads oversubscribe the cores beside worker processes)
            oo = oc[0] if shared else None
            num = self._offset[fh] - (nrm[:, 0] * oo[0] + nrm[:, 1] * oo[1] + nrm[:, 2] * oo[2] if shared
                                      else np.einsum("ij,ij->i", nrm, oc[hit]))
            good = np.abs(denom) > _GRAZING_COS * np.sqrt(np.einsum("ij,ij->i", dh, dh))
            t[hit] = num / np.where(good, denom, 1.0)
            if not good.all():  # grazing hits: ask Embree for its own (float32) distance
                g = hit[~good]
                og = o32[g]
                res = self._scene.run(og, np.ascontiguousarray(d[g], dtype=np.float32), output=1)
                t[g] = np.asarray(res["tfar"], dtype=np.float64)
        return t, face

    def first_faces(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """See :class:`Raycaster` (no distance work: the dense visibility grid needs only faces for most rays)."""
        o, d = _check_rays(origins, directions)
        if len(d) == 0:
            return np.zeros(0, dtype=np.int64)
        o32 = np.empty((len(d), 3), dtype=np.float32)
        o32[:] = (o - self.centre).astype(np.float32)
        return self._scene.run(o32, np.ascontiguousarray(d, dtype=np.float32)).astype(np.int64)


class Open3DRaycaster:
    """Open3D's ``RaycastingScene`` (also Embree inside, float32 ``t_hit``); ``--backend open3d``."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        try:
            import open3d as o3d
        except ImportError as e:  # optional dependency (open3d-cpu); report it as a user-facing one-liner
            raise InputError(f"--backend open3d needs the 'open3d' package (pip install open3d-cpu): {e}") from None
        v, f = _check_mesh(vertices, faces)
        self.centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
        self._o3d = o3d
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor((v - self.centre).astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32))
        )

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """See :class:`Raycaster`."""
        o, d = _check_rays(origins, directions)
        if len(d) == 0:
            return np.zeros(0), np.zeros(0, dtype=np.int64)
        rays = np.empty((len(d), 6), dtype=np.float32)
        rays[:, :3] = o - self.centre
        rays[:, 3:] = d
        ans = self._scene.cast_rays(self._o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy().astype(np.float64)
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        miss = ~np.isfinite(t) | (prim == self._o3d.t.geometry.RaycastingScene.INVALID_ID)
        t[miss] = np.inf
        prim[miss] = -1
        return t, prim

    def first_faces(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """See :class:`Raycaster`."""
        return self.cast(origins, directions)[1]


#: Backend name → class (the ``--backend`` choices).
BACKENDS: dict[str, type] = {"embree": EmbreeRaycaster, "open3d": Open3DRaycaster}


def make_raycaster(vertices: np.ndarray, faces: np.ndarray, backend: str = "embree") -> Raycaster:
    """Build the scene of a mesh (world frame, metres) once, with the named backend (``embree`` or ``open3d``)."""
    if backend not in BACKENDS:
        raise InputError(f"unknown raycasting backend {backend!r} (available: {', '.join(BACKENDS)})")
    return BACKENDS[backend](vertices, faces)
