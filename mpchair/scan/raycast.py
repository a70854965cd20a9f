"""First-hit raycasting of a triangle mesh behind one protocol, with two backends that give the same hits.

``cast(origins, directions) -> (t, face_id)``: origins (N,3), or (3,) shared by all rays, and directions (N,3) in the
mesh's frame (the world
frame, Matterport z up, metres; directions need not be unit); ``t`` (N,) float64 is the ray parameter of the first hit
(``hit = origin + t * direction``, so metres when directions are unit vectors, planar depth for ``(1, ., .)``
directions), ``inf`` on a miss; ``face_id`` (N,) int64 indexes the mesh's faces, -1 on a miss.

Precision: both backends work in float32. Matterport houses sit at an arbitrary global offset, so every scene is
built on a *recentred* copy of the mesh (vertices minus their bounding-box centre, in float64, then float32) and rays
are recentred the same way before the cast; float32 then resolves ~1e-6 of a house's size instead of ~1e-6 of its
offset. Directions are rounded to float32 once (float32 input is used as is); the Embree backend then recomputes
``t`` in float64 on the hit face's plane, along that float32 direction.

The scene is built once per mesh and reused for every frame. Open3D is imported only when its backend is used.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from mpchair.core.errors import InputError
from mpchair.core.jit import njit_cached
from mpchair.scan.embree import open_scene

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
    """(N,3) or (1,3) float64 origins (a (3,) origin is shared by all rays) and (N,3) contiguous float32 directions
    (both engines trace float32; float32 input passes without a copy)."""
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.ascontiguousarray(np.reshape(directions, (-1, 3)), dtype=np.float32)
    if len(o) != 1 and o.shape != d.shape:
        raise ValueError(f"origins {o.shape} and directions {d.shape} differ")
    return o, d


def _ray_origins(origins: np.ndarray, n: int) -> np.ndarray:
    """(n,3) float32 origins for embreex's ``run`` from (n,3) or (1,3) ones.

    A shared origin becomes a stride-0 view of one row instead of n copies: ``run`` only reads row i of it (it needs
    one row per ray), and a sensor's ~100k dense rays would otherwise fill 1.2 MB per call.
    """
    o32 = np.ascontiguousarray(origins, dtype=np.float32).reshape(-1, 3)
    if len(o32) == n:
        return o32
    return np.lib.stride_tricks.as_strided(o32, shape=(n, 3), strides=(0, o32.strides[1]), writeable=True)


@njit_cached
def _plane_distances(face, normal, offset, origins, directions, t):  # pragma: no cover - compiled
    """Fill ``t[i]`` with the ray parameter of ray i on the plane of its hit face ``face[i]`` (misses: left as is);
    return the (N,) bool mask of hits too grazing for the plane equation (left as is too)."""
    grazing = np.zeros(len(face), dtype=np.bool_)
    shared = origins.shape[0] == 1
    for i in range(len(face)):
        f = face[i]
        if f < 0:
            continue
        j = 0 if shared else i
        dx, dy, dz = np.float64(directions[i, 0]), np.float64(directions[i, 1]), np.float64(directions[i, 2])
        nx, ny, nz = normal[f, 0], normal[f, 1], normal[f, 2]
        denom = nx * dx + ny * dy + nz * dz
        if abs(denom) > _GRAZING_COS * np.sqrt(dx * dx + dy * dy + dz * dz):
            t[i] = (offset[f] - (nx * origins[j, 0] + ny * origins[j, 1] + nz * origins[j, 2])) / denom
        else:
            grazing[i] = True
    return grazing


class EmbreeRaycaster:
    """Embree (Intel), the engine behind trimesh's ``ray_pyembree.RayMeshIntersector``; the default. The library is
    embreex's, driven with its instruction set pinned (:mod:`mpchair.scan.embree`) where possible, else through embreex.

    The embreex scene is built directly (as trimesh's ``_EmbreeWrap`` does) rather than through
    ``RayMeshIntersector.intersects_first``, which copies and re-normalises every direction array: that overhead
    alone was about as large as the raycast itself for our ray counts. Embree returns the first hit's face id and its
    float32 ``tfar``; ``t`` is then solved in float64 on that face's plane (kept from ``tfar`` only at grazing angles,
    where the plane equation is ill-conditioned).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        v, f = _check_mesh(vertices, faces)
        self.centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
        self._v = v - self.centre
        # Embree with its ISA pinned (the same bits on AVX2 and AVX-512 CPUs: mpchair/scan/embree.py); embreex's own
        # device where no ISA is pinned or the library is not found. Both scenes have embreex's ``run``.
        self._scene = open_scene(self._v.astype(np.float32), f)
        if self._scene is None:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh

            self._scene = rtcore_scene.EmbreeScene()
            TriangleMesh(scene=self._scene, vertices=self._v.astype(np.float32), indices=f.astype(np.int32))
        a, b, c = self._v[f[:, 0]], self._v[f[:, 1]], self._v[f[:, 2]]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n, axis=1)
        self._normal = n / np.where(norm > 0, norm, 1.0)[:, None]  # unit normals (degenerate faces: zero)
        self._offset = np.einsum("ij,ij->i", self._normal, a)  # plane: n . x = offset

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """See :class:`Raycaster`."""
        o, d32 = _check_rays(origins, directions)
        n = len(d32)
        t = np.full(n, np.inf)
        if n == 0:
            return t, np.zeros(0, dtype=np.int64)
        oc = o - self.centre
        o32 = _ray_origins(oc, n)
        face = np.asarray(self._scene.run(o32, d32), dtype=np.int64)
        # t on the hit face's plane, in float64, along the float32 direction Embree traced (one compiled pass:
        # the numpy version's gathers and temporaries cost half as much as the raycast itself).
        grazing = _plane_distances(face, self._normal, self._offset, oc, d32, t)
        if grazing.any():  # grazing hits: ask Embree for its own (float32) distance
            g = np.flatnonzero(grazing)
            res = self._scene.run(np.ascontiguousarray(o32[g]), np.ascontiguousarray(d32[g]), output=1)
            t[g] = np.asarray(res["tfar"], dtype=np.float64)
        return t, face

    def first_faces(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """See :class:`Raycaster` (no distance work: the dense visibility grid needs only faces for most rays)."""
        o, d32 = _check_rays(origins, directions)
        if len(d32) == 0:
            return np.zeros(0, dtype=np.int64)
        return np.asarray(self._scene.run(_ray_origins(o - self.centre, len(d32)), d32), dtype=np.int64)


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
