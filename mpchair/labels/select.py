"""Which object boxes of one frame become labels: aligned boxes moved into the sensor frame, then the filters.

Order (first failure is the recorded reason, see :data:`mpchair.labels.filters.REJECT_REASONS`): the cheap tests on
the box centre (height, distance, field of view), then dense visibility on the camera grid (visible pixels, points
in box, in-box fraction), then the saved scan (scan points). Boxes are (N,7) ``[x, y, z, l, w, h, yaw]``, sensor frame
(x forward, y left, z up, metres) unless named ``world``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from mpchair.geometry import (
    canonical_yaw,
    invert_rigid,
    points_in_boxes,
    region_failures,
    transform_boxes,
    transform_points,
)
from mpchair.kitti import Calib
from mpchair.labels.filters import LabelFilters
from mpchair.labels.visibility import (
    COARSE_RAYS,
    ObjectScenes,
    ObjectVisibility,
    cast_pixels,
    coarse_stride,
    grid_regions,
    object_visibility,
    region_mask,
    vertex_region,
    visible_fraction,
)
from mpchair.scan.raycast import Raycaster
from mpchair.scan.sensors import CameraConfig


@dataclasses.dataclass(frozen=True)
class BoxDecisions:
    """The fate of each candidate box of a frame (arrays of length N, candidates in house object order).

    ``objects`` positions in the house's objects; ``boxes`` (N,7) sensor frame; ``reasons`` ``""`` for kept, else the
    first failed filter; ``visible_pixels``, ``points_in_box`` (dense grid counts, -1 = not evaluated),
    ``in_box_fraction`` (NaN = not evaluated), ``scan_points`` (-1 = not evaluated), ``visible_fraction`` of the
    unoccluded silhouette and ``occluded`` (KITTI 0/1/2) for kept boxes (NaN / -1 otherwise), ``regions`` (N,4)
    dense pixel regions (``[r0, r1, c0, c1]``), ``dense_rays`` the number of dense rays cast, ``exact`` (N,) bool:
    the dense counts cover the whole region (else they are lower bounds that already prove the box passes; see
    :mod:`mpchair.labels.visibility`).
    """

    objects: np.ndarray
    boxes: np.ndarray
    reasons: tuple[str, ...]
    visible_pixels: np.ndarray
    points_in_box: np.ndarray
    in_box_fraction: np.ndarray
    scan_points: np.ndarray
    visible_fraction: np.ndarray
    occluded: np.ndarray
    regions: np.ndarray
    dense_rays: int
    exact: np.ndarray

    @property
    def kept(self) -> np.ndarray:
        """(N,) bool: boxes that passed every filter."""
        return np.array([r == "" for r in self.reasons], dtype=bool)


def boxes_to_sensor(world_boxes: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(N,7) world-frame yaw-only boxes → sensor frame, for ``pose`` = (4,4) sensor → world (yaw-only rotation).

    Matterport object boxes have no front (their axes come from a fit), so the yaw is made canonical in the sensor
    frame: the long side's direction in ``[-pi/2, pi/2)`` (:func:`mpchair.geometry.canonical_yaw`), a function of
    what the sensor sees rather than of the fit's arbitrary sign, as in the original generator.
    """
    boxes = transform_boxes(np.asarray(world_boxes, dtype=np.float64).reshape(-1, 7), invert_rigid(pose))
    boxes[:, 6] = canonical_yaw(boxes[:, 6])
    return boxes


def centre_reasons(boxes: np.ndarray, filters: LabelFilters, camera: CameraConfig) -> list[str]:
    """The cheap tests on box centres (sensor frame): ``"height"``, ``"distance"``, ``"fov"`` or ``""`` (passed).

    Height: ``|z| <= max_abs_dz``; distance: ``hypot(x, y) <= max_distance``; fov: ``x > 0`` and
    ``atan2(|y|, x) < hfov / 2`` (only when ``filters.fov``): the labelled region of
    :mod:`mpchair.geometry.region`.
    """
    return region_failures(np.asarray(boxes, dtype=np.float64).reshape(-1, 7)[:, :3], filters.max_abs_dz,
                           filters.max_distance, label_half_fov(filters, camera))


def label_half_fov(filters: LabelFilters, camera: CameraConfig) -> float | None:
    """Half the horizontal field of view (radians) of the labelled region, or ``None`` when ``filters.fov`` is off."""
    return math.radians(camera.hfov_deg) / 2.0 if filters.fov else None


def occlusion_level(visible_fraction: np.ndarray, cutoffs: tuple[float, float]) -> np.ndarray:
    """KITTI ``occluded`` (0 fully visible, 1 partly, 2 largely) from the visible fraction of the silhouette."""
    f = np.asarray(visible_fraction, dtype=np.float64)
    return np.where(f >= cutoffs[0], 0, np.where(f >= cutoffs[1], 1, 2)).astype(np.int64)


def _passes(ov: ObjectVisibility, filters: LabelFilters) -> np.ndarray:
    """(N,) bool: the dense counts pass the visible-pixel, points-in-box and in-box-fraction filters."""
    return ((ov.visible_pixels > filters.min_visible_pixels) & (ov.points_in_box >= filters.min_points_in_box)
            & (ov.in_box_fraction >= filters.min_in_box_fraction))


def decide_boxes(
    world_boxes: np.ndarray,
    objects: np.ndarray,
    pose: np.ndarray,
    raycaster: Raycaster,
    face_object: np.ndarray,
    camera: CameraConfig,
    calib: Calib,
    filters: LabelFilters,
    scenes: ObjectScenes | None = None,
    cover_boxes: np.ndarray | None = None,
    outside: list[np.ndarray] | None = None,
    coarse_rays: int | None = COARSE_RAYS,
) -> BoxDecisions:
    """Run every filter except the scan-point one (see :func:`apply_scan_points`) on one frame's candidates.

    ``world_boxes`` (N,7) world frame, ``objects`` (N,) their positions in the house's objects, ``pose`` (4,4)
    sensor → world, ``raycaster`` over the whole house mesh (world frame), ``face_object`` (F,) face → object
    position. With ``scenes``, kept boxes also get their unoccluded silhouette (visible fraction, KITTI occlusion).
    ``cover_boxes`` (N,7) world (:func:`~mpchair.labels.visibility.covering_boxes`) widen the dense regions to every
    face of each object; without them the regions are the boxes' own projections. ``outside`` (per candidate, world
    vertices of the faces that can hit outside its box: :func:`~mpchair.labels.visibility.outside_vertices`) enables
    the coarse first stage with ``coarse_rays`` rays per candidate; without it, or with ``coarse_rays=None``, every
    pixel of every region is cast. The decisions are the same either way.
    """
    objects = np.asarray(objects, dtype=np.int64).reshape(-1)
    boxes = boxes_to_sensor(world_boxes, pose)
    n = len(boxes)
    reasons = centre_reasons(boxes, filters, camera)
    vis = np.full(n, -1, dtype=np.int64)
    inb = np.full(n, -1, dtype=np.int64)
    frac = np.full(n, np.nan)
    vfrac = np.full(n, np.nan)
    occ = np.full(n, -1, dtype=np.int64)
    exact = np.ones(n, dtype=bool)
    regions = np.tile(np.array([0, -1, 0, -1], dtype=np.int64), (n, 1))
    cand = np.array([r == "" for r in reasons], dtype=bool)
    dense_rays = 0
    if cand.any():
        idx = np.flatnonzero(cand)
        cover = boxes[idx] if cover_boxes is None else boxes_to_sensor(np.asarray(cover_boxes)[idx], pose)
        regions[idx] = grid_regions(cover, calib, camera)
        # Stage 1: a coarse grid of each region plus every pixel where the object could hit outside its box.
        mask = np.zeros((camera.height, camera.width), dtype=bool)
        world_to_sensor = invert_rigid(pose)
        for k in idx:
            r0, r1, c0, c1 = regions[k]
            if r1 < r0 or c1 < c0:
                continue
            s = coarse_stride(regions[k], coarse_rays if outside is not None else None)
            sub = None
            if s > 1:
                sub = vertex_region(transform_points(outside[k], world_to_sensor), camera, regions[k])
            if s == 1 or sub is None:
                mask[r0 : r1 + 1, c0 : c1 + 1] = True
                continue
            exact[k] = False
            mask[r0 : r1 + 1 : s, c0 : c1 + 1 : s] = True
            if sub[1] >= sub[0] and sub[3] >= sub[2]:
                mask[sub[0] : sub[1] + 1, sub[2] : sub[3] + 1] = True
        hits = cast_pixels(mask, camera, pose, raycaster, face_object, objects[idx])
        ov = object_visibility(hits, boxes[idx], objects[idx], filters.box_margin)
        # Stage 2: candidates not yet proven to pass get their whole region, so rejections use exact counts.
        casts = [hits]
        redo = idx[~exact[idx] & ~_passes(ov, filters)]
        if len(redo):
            more = cast_pixels(region_mask(regions[redo], camera) & ~mask, camera, pose, raycaster, face_object,
                               objects[idx])
            ov = ov + object_visibility(more, boxes[idx], objects[idx], filters.box_margin)  # disjoint pixels
            casts.append(more)
            exact[redo] = True
        dense_rays = sum(len(h.pixels) for h in casts)
        vis[idx], inb[idx], frac[idx] = ov.visible_pixels, ov.points_in_box, ov.in_box_fraction
        for j, k in enumerate(idx):
            if ov.visible_pixels[j] <= filters.min_visible_pixels:
                reasons[k] = "visible_pixels"
            elif ov.points_in_box[j] < filters.min_points_in_box:
                reasons[k] = "points_in_box"
            elif ov.in_box_fraction[j] < filters.min_in_box_fraction:
                reasons[k] = "in_box_fraction"
            elif scenes is not None:
                vfrac[k] = visible_fraction(scenes, int(objects[k]), regions[k], casts, camera, pose)
                occ[k] = int(occlusion_level(np.array([vfrac[k]]), filters.occlusion_cutoffs)[0])
    return BoxDecisions(objects, boxes, tuple(reasons), vis, inb, frac, np.full(n, -1, dtype=np.int64), vfrac, occ,
                        regions, dense_rays, exact)


def apply_scan_points(decisions: BoxDecisions, points: np.ndarray, filters: LabelFilters) -> BoxDecisions:
    """Count the saved scan's points (M,3+, sensor frame) inside each surviving box; reject below
    ``min_scan_points``."""
    kept = decisions.kept
    scan = decisions.scan_points.copy()
    reasons = list(decisions.reasons)
    if kept.any():
        idx = np.flatnonzero(kept)
        inside = points_in_boxes(np.asarray(points)[:, :3].astype(np.float64), decisions.boxes[idx])
        scan[idx] = inside.sum(axis=1)
        for k in idx:
            if scan[k] < filters.min_scan_points:
                reasons[k] = "scan_points"
    occ = np.where(np.array([r == "" for r in reasons], dtype=bool), decisions.occluded, -1)
    return dataclasses.replace(decisions, reasons=tuple(reasons), scan_points=scan, occluded=occ)
