"""Embree 4 with its instruction set pinned: the same first hits, bit for bit, on every x86-64 CPU with AVX2.

Embree picks its traversal and intersection kernels from the CPU at run time (SSE4.2, AVX, AVX2, AVX-512), and the
kernels round differently: on one house, 8.7 % of 100,000 random rays got another float32 ``tfar`` and 1 in 100,000
another triangle (a ray through a shared edge) with the AVX2 kernels than with the AVX-512 ones. A dataset made on
an AVX-512 CPU therefore differed in float bits from the same command's dataset on an AVX2 one (the accuracy study's
12-house dataset: sha256 ``2c1c263a3dae`` against ``11af74cae028``). embreex, the binding trimesh uses, creates its
device without a configuration, so it cannot choose; this module opens the Embree library that embreex ships and
creates the device with ``isa=avx2`` wherever the CPU runs AVX2 (every AVX-512 CPU does). With it, the AVX-512 EPYC
regenerated the AVX2 machine's dataset byte for byte (docs/generate.md, "Determinism").

Everything else is embreex's setup, so that results equal embreex's on the same ISA (``tests/test_scan_embree.py``
checks it against embreex on this CPU's own ISA): a robust static scene (``RTC_SCENE_FLAG_ROBUST``, what embreex sets),
one triangle geometry in Embree-owned float32 / uint32 buffers, ``rtcIntersect1`` per ray with ``tnear = 0``,
``tfar = 1e37``, all mask bits. The per-ray loop is compiled with numba (it calls the C function directly).

``MPCHAIR_EMBREE_ISA`` overrides the pin: an Embree ISA name (``sse4.2``, ``avx``, ``avx2``, ``avx512``) or
``native`` (Embree's own choice). Where the library cannot be found (embreex's wheel layout for another platform) or
the CPU lacks AVX2, :func:`open_scene` returns None and the caller uses embreex itself (then results can differ in
float bits from an AVX2 machine's).
"""

from __future__ import annotations

import ctypes
import functools
import platform
import sys
from pathlib import Path

import numpy as np

from mpchair.core.cpu import cpu_flags
from mpchair.core.limits import embree_isa_env

#: The ISA pinned on x86-64 CPUs with AVX2 (Embree's name).
PINNED_ISA = "avx2"
_ROBUST = 4  # RTC_SCENE_FLAG_ROBUST
_TRIANGLE = 0  # RTC_GEOMETRY_TYPE_TRIANGLE
_INDEX, _VERTEX = 0, 1  # RTC_BUFFER_TYPE_*
_UINT3, _FLOAT3 = 0x5003, 0x9003  # RTC_FORMAT_*
_INVALID = 0xFFFFFFFF
_TFAR0 = np.float32(1e37)  # embreex's initial tfar (also what a miss keeps)


def _cpu_has_avx2() -> bool:
    """Whether the CPU runs Embree's AVX2 kernels (AVX2, FMA, BMI1/2 and LZCNT, which /proc/cpuinfo calls abm)."""
    flags = cpu_flags()
    return {"avx2", "fma", "bmi1", "bmi2"} <= flags and bool({"abm", "lzcnt"} & flags)


def requested_isa() -> str | None:
    """The ISA to pin (Embree's name), or None for Embree's own choice: ``MPCHAIR_EMBREE_ISA`` if set (validated),
    else :data:`PINNED_ISA` on Linux x86-64 CPUs with AVX2, else None."""
    env = embree_isa_env()
    if env is not None:
        return None if env == "native" else env
    if sys.platform == "linux" and platform.machine() in ("x86_64", "AMD64") and _cpu_has_avx2():
        return PINNED_ISA
    return None


def _library_path() -> Path | None:
    """The Embree 4 shared library bundled with embreex (Linux wheels: ``embreex.libs/libembree4-*.so.4``)."""
    try:
        import embreex
    except ImportError:
        return None
    pkg = Path(embreex.__file__).resolve().parent
    for folder, pattern in ((pkg.parent / "embreex.libs", "libembree4*.so*"), (pkg / ".dylibs", "libembree4*.dylib"),
                            (pkg, "libembree4*.so*")):
        found = sorted(folder.glob(pattern)) if folder.is_dir() else []
        if found:
            return found[0]
    return None


@functools.cache
def _api():
    """(the ctypes library, the compiled per-ray loop), or None where the library cannot be opened."""
    path = _library_path()
    if path is None:
        return None
    try:
        lib = ctypes.CDLL(str(path))
    except OSError:
        return None
    vp, u, sz = ctypes.c_void_p, ctypes.c_uint, ctypes.c_size_t
    for name, res, args in (
        ("rtcNewDevice", vp, [ctypes.c_char_p]), ("rtcReleaseDevice", None, [vp]),
        ("rtcGetDeviceError", ctypes.c_int, [vp]),
        ("rtcNewScene", vp, [vp]), ("rtcSetSceneFlags", None, [vp, ctypes.c_int]), ("rtcCommitScene", None, [vp]),
        ("rtcReleaseScene", None, [vp]),
        ("rtcNewGeometry", vp, [vp, ctypes.c_int]), ("rtcSetNewGeometryBuffer", vp, [vp, ctypes.c_int, u, ctypes.c_int,
                                                                                      sz, sz]),
        ("rtcCommitGeometry", None, [vp]), ("rtcAttachGeometry", u, [vp, vp]), ("rtcReleaseGeometry", None, [vp]),
    ):
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = res, args
    # rtcIntersect1(RTCScene, RTCRayHit*, RTCIntersectArguments*): pointers passed as integers from the loop
    intersect1 = ctypes.CFUNCTYPE(None, sz, sz, sz)(ctypes.cast(lib.rtcIntersect1, vp).value)
    return lib, _compile_loop(intersect1)


def _compile_loop(intersect1):
    """The per-ray loop over ``intersect1`` (numba; not cached on disk: it holds the library's address)."""
    import numba

    @numba.njit(nogil=True)
    def trace(scene, origins, shared, directions, buf, face, tfar):  # pragma: no cover - compiled
        # RTCRayHit, 16-byte aligned inside buf: ray (org, tnear, dir, time, tfar, mask, id, flags) = floats 0..11,
        # hit (Ng, u, v, primID, geomID, instID, instPrimID) = 12..20
        addr = buf.ctypes.data
        skip = ((16 - addr % 16) % 16) // 4
        r = buf[skip:skip + 32]
        ri = r.view(np.uint32)
        addr += skip * 4
        for i in range(directions.shape[0]):
            j = 0 if shared else i
            r[0] = origins[j, 0]
            r[1] = origins[j, 1]
            r[2] = origins[j, 2]
            r[3] = 0.0
            r[4] = directions[i, 0]
            r[5] = directions[i, 1]
            r[6] = directions[i, 2]
            r[7] = 0.0
            r[8] = np.float32(1e37)
            ri[9] = 0xFFFFFFFF
            ri[10] = 0
            ri[11] = 0
            for k in range(17, 21):
                ri[k] = 0xFFFFFFFF
            intersect1(scene, addr, 0)
            face[i] = -1 if ri[18] == 0xFFFFFFFF else np.int64(ri[17])
            tfar[i] = r[8]

    return trace


class PinnedEmbreeScene:
    """One triangle mesh (float32 vertices, recentred by the caller) in an Embree device of ISA ``isa`` (Embree's
    name; None: Embree's own choice, as embreex does)."""

    def __init__(self, vertices32: np.ndarray, faces: np.ndarray, isa: str | None):
        lib, self._trace = _api()
        self._lib = lib
        self.isa = isa or "native"
        self._device = lib.rtcNewDevice(f"isa={isa}".encode() if isa else None)
        if not self._device:
            raise RuntimeError(f"Embree could not create a device with isa={isa}")
        self._scene = None
        v = np.ascontiguousarray(vertices32, dtype=np.float32)
        f = np.ascontiguousarray(faces, dtype=np.uint32)
        self._scene = lib.rtcNewScene(self._device)
        lib.rtcSetSceneFlags(self._scene, _ROBUST)
        geom = lib.rtcNewGeometry(self._device, _TRIANGLE)
        vbuf = lib.rtcSetNewGeometryBuffer(geom, _VERTEX, 0, _FLOAT3, 12, len(v))
        ibuf = lib.rtcSetNewGeometryBuffer(geom, _INDEX, 0, _UINT3, 12, len(f))
        if not vbuf or not ibuf:
            raise RuntimeError(f"Embree could not allocate buffers (error {lib.rtcGetDeviceError(self._device)})")
        ctypes.memmove(vbuf, v.ctypes.data, v.nbytes)
        ctypes.memmove(ibuf, f.ctypes.data, f.nbytes)
        lib.rtcCommitGeometry(geom)
        lib.rtcAttachGeometry(self._scene, geom)
        lib.rtcReleaseGeometry(geom)  # the scene holds it
        lib.rtcCommitScene(self._scene)
        err = lib.rtcGetDeviceError(self._device)
        if err:
            raise RuntimeError(f"Embree error {err} building the scene")
        self._buf = np.zeros(48, dtype=np.float32)

    def run(self, origins32: np.ndarray, directions32: np.ndarray, output: int | None = None):
        """The first hit of each ray, as embreex's ``EmbreeScene.run`` gives it: origins (N,3) or (1,3) (or a stride-0
        view of one row) and directions (N,3) float32 in the scene's (recentred) frame; returns the hit faces (N,)
        int64 (-1 on a miss), or with ``output`` a dict of ``primID`` (the same) and ``tfar`` (N,) float32 (1e37 on
        a miss)."""
        d = np.ascontiguousarray(directions32, dtype=np.float32)
        n = len(d)
        shared = origins32.shape[0] != n or origins32.strides[0] == 0
        o = np.ascontiguousarray(origins32[:1] if shared else origins32, dtype=np.float32)
        face = np.empty(n, dtype=np.int64)
        tfar = np.empty(n, dtype=np.float32)
        if n:
            self._trace(self._scene, o, shared, d, self._buf, face, tfar)
        return {"primID": face, "tfar": tfar} if output else face

    def __del__(self):
        lib = getattr(self, "_lib", None)
        if lib is None:
            return
        if getattr(self, "_scene", None):
            lib.rtcReleaseScene(self._scene)
            self._scene = None
        if getattr(self, "_device", None):
            lib.rtcReleaseDevice(self._device)
            self._device = None


def open_scene(vertices32: np.ndarray, faces: np.ndarray, isa: str | None = None) -> PinnedEmbreeScene | None:
    """A scene of the pinned ISA (``isa``, default :func:`requested_isa`), or None where no ISA is to be pinned or
    the library cannot be opened (the caller then uses embreex)."""
    isa = isa if isa is not None else requested_isa()
    if isa is None or _api() is None:
        return None
    try:
        return PinnedEmbreeScene(vertices32, faces, isa)
    except RuntimeError:  # e.g. a CPU without that ISA: Embree refuses the device
        return None
