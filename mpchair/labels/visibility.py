"""Dense visibility on the virtual camera's full-resolution pixel grid, cast only where it matters.

The original filters counted an object's pixels on a rendered 1024 x 1024 instance image. Here the same grid
(:func:`mpchair.scan.sensors.grid_directions`) is raycast, but only inside the candidates' projected 2D boxes (their
union, each pixel once): an object's pixels can only fall inside the projection of the box that covers all its faces
(a 2-pixel margin covers the half-pixel difference between the grid and the ``P2`` pinhole).

Even that is ~200k rays per frame when chairs are near, so the filters are decided in two stages that give exactly the
decisions of the full grid (``tests/test_labels.py`` compares them):

1. a coarse, regular subset of each region (stride chosen for at most :data:`COARSE_RAYS` rays), plus *every* pixel of
   the region where a hit on the object could land outside its box: the projection of the object's faces that are not
   wholly inside the box (a hit on a face inside the convex box is inside it). Counts over a subset of the grid are
   lower bounds of the full counts, and the out-of-box count is already exact, so ``visible > 35``,
   ``in_box >= 35`` and ``in_box / visible >= 0.8`` hold on the full grid whenever they hold for the lower bounds;
2. only candidates not yet shown to pass get their whole region cast, so every rejection is decided on exact counts.

A kept box's ``visible_pixels`` is therefore exact or a lower bound (``BoxDecisions.exact`` says which).

Points are in the sensor frame (x forward, y left, z up, metres); pixel regions are inclusive ``[r0, r1] x [c0, c1]``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from mpchair.core.jit import njit_cached
from mpchair.geometry import points_in_boxes, project_boxes_to_image
from mpchair.kitti import Calib
from mpchair.scan.grid_rays import mask_rays
from mpchair.scan.raycast import Raycaster, make_raycaster
from mpchair.scan.sensors import CameraConfig, grid_directions

#: Pixels added around each projected box before casting (covers grid vs P2 rounding; see module docstring).
REGION_MARGIN = 2
#: At most about this many rays per candidate in the coarse stage and for the unoccluded silhouette.
COARSE_RAYS = 4096


@dataclasses.dataclass(frozen=True)
class DenseHits:
    """Dense camera-grid rays cast in one frame: ``pixels`` (P,) int64 increasing row-major grid indices
    (``row * W + col``) of every ray cast; of those that hit a requested object: ``picked`` (K,) int64 indices into
    ``pixels``, ``object`` (K,) int64 the object position hit and ``points`` (K,3) the sensor-frame hit points
    (metres)."""

    pixels: np.ndarray
    picked: np.ndarray
    object: np.ndarray
    points: np.ndarray


def objects_at(casts: list[DenseHits], pixels: np.ndarray) -> np.ndarray:
    """(K,) int64 requested object hit at grid ``pixels`` (flat indices) in disjoint ``casts``, -1 where none (not
    cast, or no requested object there). A binary search in each cast's sorted pixels: no full-grid image."""
    out = np.full(len(pixels), -1, dtype=np.int64)
    for h in casts:
        if len(h.picked) == 0:
            continue
        hp = h.pixels[h.picked]
        i = np.minimum(np.searchsorted(hp, pixels), len(hp) - 1)
        found = hp[i] == pixels
        out[found] = h.object[i[found]]
    return out


@njit_cached
def _requested_hits(face, face_object, requested):  # pragma: no cover - compiled
    """Indices of the rays whose hit face belongs to an object with ``requested[object]`` (faces -1: misses)."""
    out = np.empty(len(face), dtype=np.int64)
    k = 0
    for i in range(len(face)):
        f = face[i]
        if f >= 0:
            o = face_object[f]
            if 0 <= o < len(requested) and requested[o]:
                out[k] = i
                k += 1
    return out[:k].copy()


def _faces_by_object(faces: np.ndarray, face_object: np.ndarray, objects: np.ndarray):
    """Yield the (K,3) faces of each object position in ``objects``, in order (one stable sort for all of them)."""
    order = np.argsort(face_object, kind="stable")
    sorted_obj = face_object[order]
    for obj in np.asarray(objects).reshape(-1):
        lo, hi = np.searchsorted(sorted_obj, obj, "left"), np.searchsorted(sorted_obj, obj, "right")
        yield faces[order[lo:hi]]


def covering_boxes(
    vertices: np.ndarray, faces: np.ndarray, face_object: np.ndarray, objects: np.ndarray, boxes: np.ndarray
) -> np.ndarray:
    """(N,7) world boxes with the yaw of ``boxes`` that cover both each box and every vertex of its object's faces.

    Dense regions are cast over these, so an object's pixels are all counted even where its labelled faces stray
    outside its annotated box (the "holes / label noise" case the in-box fraction exists for). ``objects`` (N,) are
    object positions (``face_object`` values), ``boxes`` (N,7) their aligned boxes, world frame.
    """
    out = np.asarray(boxes, dtype=np.float64).reshape(-1, 7).copy()
    for k, f in enumerate(_faces_by_object(faces, face_object, objects)):
        if len(f) == 0:
            continue
        v = vertices[np.unique(f.reshape(-1))] - out[k, :3]
        c, s = np.cos(out[k, 6]), np.sin(out[k, 6])
        local = np.column_stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1], v[:, 2]])
        half = out[k, 3:6] / 2
        lo3 = np.minimum(local.min(axis=0), -half)
        hi3 = np.maximum(local.max(axis=0), half)
        mid = (lo3 + hi3) / 2
        out[k, 0] += c * mid[0] - s * mid[1]
        out[k, 1] += s * mid[0] + c * mid[1]
        out[k, 2] += mid[2]
        out[k, 3:6] = hi3 - lo3
    return out


def grid_regions(boxes: np.ndarray, calib: Calib, camera: CameraConfig) -> np.ndarray:
    """(N,4) int64 inclusive pixel regions ``[r0, r1, c0, c1]`` of (N,7) sensor-frame boxes on the camera grid.

    The projected, clipped 2D box of each box (parts behind the camera are cut off by the geometry module), widened by
    :data:`REGION_MARGIN`. A box wholly outside the image gets an empty region (``r1 < r0``).
    """
    bbox, trunc = project_boxes_to_image(boxes, calib, (camera.width, camera.height))
    out = np.empty((len(boxes), 4), dtype=np.int64)
    out[:, 0] = np.floor(bbox[:, 1]) - REGION_MARGIN
    out[:, 1] = np.ceil(bbox[:, 3]) + REGION_MARGIN
    out[:, 2] = np.floor(bbox[:, 0]) - REGION_MARGIN
    out[:, 3] = np.ceil(bbox[:, 2]) + REGION_MARGIN
    out[:, [0, 1]] = np.clip(out[:, [0, 1]], 0, camera.height - 1)
    out[:, [2, 3]] = np.clip(out[:, [2, 3]], 0, camera.width - 1)
    out[trunc >= 1.0] = (0, -1, 0, -1)
    return out


def coarse_stride(region: np.ndarray, max_rays: int | None = COARSE_RAYS) -> int:
    """Grid stride of the coarse stage for an inclusive pixel ``region`` (1 = every pixel; ``max_rays=None``: 1)."""
    r0, r1, c0, c1 = (int(v) for v in region)
    if max_rays is None or r1 < r0 or c1 < c0:
        return 1
    area = (r1 - r0 + 1) * (c1 - c0 + 1)
    return max(1, int(np.ceil(np.sqrt(area / max_rays))))


def outside_vertices(
    vertices: np.ndarray, faces: np.ndarray, face_object: np.ndarray, objects: np.ndarray, boxes: np.ndarray,
    margin: float,
) -> list[np.ndarray]:
    """Per object, the (K,3) world vertices of its faces not wholly inside its box with every face pushed out by
    ``margin`` / 2.

    Only these faces can give hits outside the box pushed out by ``margin`` (the in-box test of
    :func:`object_visibility`), since a triangle with its corners inside a box lies inside it; the other half of the
    margin absorbs the float rounding of hit points. ``objects`` (N,)
    object positions (``face_object`` values), ``boxes`` (N,7) their aligned world boxes.
    """
    from mpchair.geometry import points_in_boxes

    out = []
    for k, f in enumerate(_faces_by_object(faces, face_object, objects)):
        grown = np.asarray(boxes[k : k + 1], dtype=np.float64).copy()
        grown[0, 3:6] += margin
        inside = points_in_boxes(vertices[f.reshape(-1)], grown)[0].reshape(-1, 3).all(axis=1)
        out.append(vertices[np.unique(f[~inside].reshape(-1))])
    return out


def vertex_region(points: np.ndarray, camera: CameraConfig, region: np.ndarray) -> np.ndarray | None:
    """Inclusive grid region ``[r0, r1, c0, c1]`` covering the projections of (K,3) sensor-frame ``points``, clipped to
    ``region``; ``None`` when a point is not in front of the sensor (no finite projection: use the whole region)."""
    from mpchair.scan.sensors import grid_pixels_of

    if len(points) == 0:
        return np.array([0, -1, 0, -1], dtype=np.int64)
    if (points[:, 0] <= 1e-3).any():
        return None
    rows, cols = grid_pixels_of(camera, points)
    r0, r1, c0, c1 = (int(v) for v in region)
    out = np.array([np.floor(rows.min()) - REGION_MARGIN, np.ceil(rows.max()) + REGION_MARGIN,
                    np.floor(cols.min()) - REGION_MARGIN, np.ceil(cols.max()) + REGION_MARGIN])
    return np.array([max(out[0], r0), min(out[1], r1), max(out[2], c0), min(out[3], c1)], dtype=np.int64)


def cast_pixels(
    mask: np.ndarray,
    camera: CameraConfig,
    pose: np.ndarray,
    raycaster: Raycaster,
    face_object: np.ndarray,
    objects: np.ndarray | None = None,
) -> DenseHits:
    """Cast every grid pixel set in ``mask`` (H,W bool) once, from the sensor at ``pose`` (4,4 sensor → world).

    ``face_object`` (F,) int64 maps the mesh's faces to object positions (-1 none). Pixels come back row-major
    (increasing flat index). Points are computed only for pixels that hit one of ``objects`` (every hit when ``None``):
    ``DenseHits.picked``.
    """
    pixels, dw = mask_rays(mask, camera, pose[:3, :3])
    p = pose[:3, 3]
    face = raycaster.first_faces(p, dw)
    if objects is None:
        picked = np.flatnonzero(face >= 0)
    else:
        objects = np.asarray(objects, dtype=np.int64)
        requested = np.zeros(int(objects.max(initial=-1)) + 1, dtype=bool)
        requested[objects] = True
        picked = _requested_hits(face, np.ascontiguousarray(face_object, dtype=np.int64), requested)
    # Exact distances only where the in-box test needs them; t is along the sensor-frame direction too.
    t, _ = raycaster.cast(p, dw[picked])
    rows, cols = np.divmod(pixels[picked], camera.width)
    pts = t[:, None] * grid_directions(camera, rows, cols)
    return DenseHits(pixels, picked, face_object[face[picked]].astype(np.int64), pts)


def region_mask(regions: np.ndarray, camera: CameraConfig) -> np.ndarray:
    """(H,W) bool union of inclusive pixel ``regions`` (N,4) ``[r0, r1, c0, c1]`` (empty ones skipped)."""
    mask = np.zeros((camera.height, camera.width), dtype=bool)
    for r0, r1, c0, c1 in np.asarray(regions, dtype=np.int64).reshape(-1, 4):
        if r1 >= r0 and c1 >= c0:
            mask[r0 : r1 + 1, c0 : c1 + 1] = True
    return mask


def cast_dense(
    regions: np.ndarray,
    camera: CameraConfig,
    pose: np.ndarray,
    raycaster: Raycaster,
    face_object: np.ndarray,
    objects: np.ndarray | None = None,
) -> DenseHits:
    """Cast every grid pixel in the union of ``regions`` once (see :func:`cast_pixels`)."""
    return cast_pixels(region_mask(regions, camera), camera, pose, raycaster, face_object, objects)


@dataclasses.dataclass(frozen=True)
class ObjectVisibility:
    """Per-candidate dense counts: ``visible_pixels`` (N,) object pixels seen; ``points_in_box`` (N,) of those whose
    back-projected point lies inside the object's box; ``in_box_fraction`` (N,) their ratio (0 when none seen).

    Counts of disjoint pixel sets add up: ``a + b`` is the visibility over both."""

    visible_pixels: np.ndarray
    points_in_box: np.ndarray
    in_box_fraction: np.ndarray

    @staticmethod
    def of_counts(visible: np.ndarray, in_box: np.ndarray) -> ObjectVisibility:
        with np.errstate(divide="ignore", invalid="ignore"):
            frac = np.where(visible > 0, in_box / np.maximum(visible, 1), 0.0)
        return ObjectVisibility(visible, in_box, frac)

    def __add__(self, other: ObjectVisibility) -> ObjectVisibility:
        return ObjectVisibility.of_counts(self.visible_pixels + other.visible_pixels,
                                          self.points_in_box + other.points_in_box)


def object_visibility(hits: DenseHits, boxes: np.ndarray, objects: np.ndarray, margin: float = 0.0) -> ObjectVisibility:
    """Counts of each candidate object (``objects`` (N,) positions, ``boxes`` (N,7) sensor frame) in ``hits`` (cast
    with those objects requested).

    ``margin`` (metres) enlarges every box side for the in-box test (hits on the box's own faces are on its boundary
    and float rounding would put half of them outside).
    """
    n = len(objects)
    vis = np.zeros(n, dtype=np.int64)
    inb = np.zeros(n, dtype=np.int64)
    for k in range(n):
        sel = hits.object == objects[k]
        vis[k] = int(np.count_nonzero(sel))
        if vis[k]:
            grown = boxes[k : k + 1].copy()
            grown[0, 3:6] += 2.0 * margin
            inb[k] = int(np.count_nonzero(points_in_boxes(hits.points[sel], grown)[0]))
    return ObjectVisibility.of_counts(vis, inb)


class ObjectScenes:
    """Lazily built raycasting scenes of single objects (for their unoccluded silhouettes); one per house.

    ``vertices`` (V,3) / ``faces`` (F,3) world frame, ``face_object`` (F,) object positions.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, face_object: np.ndarray, backend: str = "embree"):
        self._v = vertices
        self._f = faces
        self._face_object = face_object
        self._backend = backend
        self._cache: dict[int, Raycaster | None] = {}

    def get(self, obj: int) -> Raycaster | None:
        """The scene of object ``obj`` alone (``None`` if it has no faces)."""
        if obj not in self._cache:
            faces = self._f[self._face_object == obj]
            if len(faces) == 0:
                self._cache[obj] = None
            else:
                used, inv = np.unique(faces.reshape(-1), return_inverse=True)
                self._cache[obj] = make_raycaster(self._v[used], inv.reshape(-1, 3), self._backend)
        return self._cache[obj]


def visible_fraction(
    scenes: ObjectScenes,
    obj: int,
    region: np.ndarray,
    casts: list[DenseHits],
    camera: CameraConfig,
    pose: np.ndarray,
) -> float:
    """Fraction of object ``obj``'s unoccluded silhouette that is visible in the dense ``casts`` (1.0 if it has none).

    Evaluated on the coarse grid of ``region`` (:func:`coarse_stride`, at most about :data:`COARSE_RAYS` rays cast
    against the object alone; those pixels were all cast in the dense stage): visible = pixels whose dense hit is
    ``obj``, unoccluded = pixels whose ray hits ``obj`` when nothing else is there.
    """
    scene = scenes.get(obj)
    r0, r1, c0, c1 = (int(v) for v in region)
    if scene is None or r1 < r0 or c1 < c0:
        return 1.0
    stride = coarse_stride(region)
    mask = np.zeros((camera.height, camera.width), dtype=bool)
    mask[r0 : r1 + 1 : stride, c0 : c1 + 1 : stride] = True
    pixels, dw = mask_rays(mask, camera, pose[:3, :3])
    full = scene.first_faces(pose[:3, 3], dw) >= 0
    n_full = int(np.count_nonzero(full))
    if n_full == 0:
        return 1.0
    return float(np.count_nonzero(objects_at(casts, pixels[full]) == obj)) / n_full
