"""One frame: pick a viewpoint, decide the labels, cast the scan, write the KITTI files and the frame record.

A frame is a pure function of ``(seed, house id, frame index)``: its generator is
``numpy.random.default_rng([seed, crc32(house_id), index])`` and draws viewpoint candidates until one is valid and
(unless ``keep_empty``) keeps at least one box, within ``max_attempts`` candidates.

Frames: the scan and boxes are in the sensor frame (x forward, y left, z up, metres); the pose is sensor → world
(Matterport, z up, metres).
"""

from __future__ import annotations

import dataclasses
import functools
import zlib
from pathlib import Path

import numpy as np

from mpchair.core.atomic import write_bytes, write_text
from mpchair.core.errors import InputError
from mpchair.core.jit import njit_cached
from mpchair.dataset.image import depth_image, png_bytes
from mpchair.dataset.manifest import FrameRecord, KeptBox, RejectedBox
from mpchair.geometry import boxes_to_kitti_camera, project_boxes_to_image, rotate_vectors
from mpchair.kitti import DONTCARE, Calib, Labels, format_calib, frame_paths, write_labels, write_velodyne
from mpchair.labels.filters import OUTSIDE_REGION_REASONS, LabelFilters
from mpchair.labels.select import BoxDecisions, apply_scan_points, decide_boxes
from mpchair.labels.visibility import ObjectScenes, cast_pixels, covering_boxes, outside_vertices
from mpchair.matterport.categories import resolve_category
from mpchair.matterport.house import House
from mpchair.scan.navmesh import NavmeshSampler
from mpchair.scan.raycast import Raycaster, make_raycaster
from mpchair.scan.sensors import CameraConfig, SensorConfig, camera_calib
from mpchair.scan.viewpoints import (
    FloorArea,
    FloorSampler,
    PointSampler,
    Viewpoint,
    ViewpointParams,
    face_normals_z,
    validate_candidates,
    viewpoint_stream,
)

#: Region labels whose floors are never sampled: junk (mirror ghosts), outdoor, stairs, unlabelled.
SKIP_REGION_LABELS = ("Z", "x", "s", "-")
#: The constant 4th velodyne channel (the sensor has no intensity; KITTI readers expect 4 floats per point).
REFLECTANCE = 1.0


def kitti_name(mpcat40_name: str) -> str:
    """KITTI type of an mpcat40 class: capitalised first letter, no spaces (``chair`` → ``Chair``)."""
    s = mpcat40_name.replace(" ", "_")
    return s[:1].upper() + s[1:]


def floor_areas(house: House, skip_labels: tuple[str, ...] = SKIP_REGION_LABELS) -> list[FloorArea]:
    """Floor polygons of the house's regions (world frame), skipping ``skip_labels`` regions.

    Houses without region floor polygons fall back to their upward-facing ``floor``-category faces, one triangle each.
    """
    areas = [
        FloorArea(r.floor_polygon, float(r.floor_z), r.level, r.index)
        for r in house.regions
        if r.label not in skip_labels and len(r.floor_polygon) >= 3
    ]
    if areas:
        return areas
    floor = resolve_category("floor")
    nz = face_normals_z(house.vertices, house.faces)
    for f in np.flatnonzero((house.face_category == floor) & (nz > 0.9)):
        tri = house.vertices[house.faces[f]]
        areas.append(FloorArea(tri[:, :2].copy(), float(tri[:, 2].mean())))
    return areas


#: Where viewpoint candidates come from: ``regions`` (the .house floor polygons), ``navmesh`` (habitat's navmesh
#: islands), ``auto`` (the navmesh when the house has one, else regions).
VIEWPOINT_SOURCES = ("auto", "regions", "navmesh")


def resolve_viewpoints(house: House, requested: str) -> str:
    """``regions`` or ``navmesh`` for ``house`` (``requested`` one of :data:`VIEWPOINT_SOURCES`); asking for the
    navmesh of a house without one is an :class:`InputError`."""
    if requested not in VIEWPOINT_SOURCES:
        raise InputError(f"--viewpoints must be one of {', '.join(VIEWPOINT_SOURCES)}, got {requested!r}")
    if requested == "auto":
        return "navmesh" if house.navmesh is not None else "regions"
    if requested == "navmesh" and house.navmesh is None:
        raise InputError(f"house {house.id} has no <id>.navmesh (habitat layout); use --viewpoints regions")
    return requested


def viewpoint_sampler(house: House, source: str) -> PointSampler:
    """The candidate sampler of ``house`` for ``source`` (``regions`` or ``navmesh``, see :func:`resolve_viewpoints`);
    a house without floor to stand on, or whose navmesh has no island of radius >= 1.5 m, is an :class:`InputError`."""
    try:
        if source == "navmesh":
            return NavmeshSampler(house.navmesh)
        areas = floor_areas(house)
        if not areas:
            raise InputError(f"house {house.id} has no floor polygon and no floor faces to place the robot on")
        return FloorSampler(areas)
    except ValueError as e:
        raise InputError(f"house {house.id}: {e}") from None


@dataclasses.dataclass
class HouseContext:
    """Everything a worker needs to make frames of one house; the raycasting scene is built once here."""

    house: House
    raycaster: Raycaster
    sampler: PointSampler
    floor_ok: np.ndarray
    normal_z: np.ndarray
    class_objects: np.ndarray
    class_boxes: np.ndarray
    cover_boxes: np.ndarray
    outside: list[np.ndarray]
    scenes: ObjectScenes


def build_context(
    house: House, categories: frozenset[int], backend: str = "embree", box_margin: float = LabelFilters.box_margin,
    viewpoints: str = "auto",
) -> HouseContext:
    """Scene, viewpoint sampler and class objects of ``house`` (``categories``: mpcat40 indices to label;
    ``box_margin`` the filters' in-box margin, metres, for the faces that can hit outside their box; ``viewpoints``
    one of :data:`VIEWPOINT_SOURCES`).

    A house with no object of the classes, or without any floor to stand on, is an :class:`InputError`.
    """
    objs = np.array([i for i, o in enumerate(house.objects) if o.mpcat40_index in categories], dtype=np.int64)
    if len(objs) == 0:
        from mpchair.matterport.categories import mpcat40_name

        names = ", ".join(sorted(mpcat40_name(c) for c in categories))
        raise InputError(f"house {house.id} has no object of class {names} (it has: "
                         f"{', '.join(f'{k} {v}' for k, v in house.objects_by_category().items()) or 'no objects'})")
    sampler = viewpoint_sampler(house, resolve_viewpoints(house, viewpoints))
    floor = resolve_category("floor")
    floor_ok = (house.face_category == floor) | (house.face_object < 0)
    boxes = np.stack([house.objects[i].aligned_box for i in objs]).astype(np.float64)
    return HouseContext(
        house=house,
        raycaster=make_raycaster(house.vertices, house.faces, backend),
        sampler=sampler,
        floor_ok=floor_ok,
        normal_z=face_normals_z(house.vertices, house.faces),
        class_objects=objs,
        class_boxes=boxes,
        cover_boxes=covering_boxes(house.vertices, house.faces, house.face_object, objs, boxes),
        outside=outside_vertices(house.vertices, house.faces, house.face_object, objs, boxes, box_margin),
        scenes=ObjectScenes(house.vertices, house.faces, house.face_object, backend),
    )


@dataclasses.dataclass(frozen=True)
class FrameSettings:
    """What every frame of a run shares: sensor profile, viewpoint parameters and candidate source
    (:data:`VIEWPOINT_SOURCES`), seed and acceptance rules."""

    sensor: SensorConfig
    viewpoints: ViewpointParams
    seed: int
    keep_empty: bool = False
    max_attempts: int = 400
    viewpoint_source: str = "auto"


@dataclasses.dataclass(frozen=True)
class FrameResult:
    """One accepted frame: its ``viewpoint``, box ``decisions``, ``points`` (M,4) float32 sensor frame
    ``[x, y, z, 1]``, ``views_tried`` (valid viewpoints evaluated, the last one accepted), ``rays`` cast in total."""

    viewpoint: Viewpoint
    decisions: BoxDecisions
    points: np.ndarray
    views_tried: int
    rays: int


def frame_rng(seed: int, house_id: str, index: int) -> np.random.Generator:
    """The generator of frame ``index`` of ``house_id``: ``default_rng([seed, crc32(house_id), index])``."""
    return np.random.default_rng([seed, zlib.crc32(house_id.encode("utf-8")), index])


@njit_cached
def _scan_points(t, face, directions, planar, min_range, max_range, z_min, z_max, reflectance):  # pragma: no cover
    """(M,4) float32 ``[x, y, z, reflectance]`` of the hits within the range limits and the open z crop."""
    out = np.empty((len(t), 4), dtype=np.float32)
    m = 0
    for i in range(len(t)):
        if face[i] < 0:
            continue
        dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
        r = t[i] * dx if planar else t[i] * np.sqrt(dx * dx + dy * dy + dz * dz)
        z = t[i] * dz
        if r < min_range or r > max_range or not (z_min < z < z_max):
            continue
        out[m, 0], out[m, 1], out[m, 2], out[m, 3] = t[i] * dx, t[i] * dy, z, reflectance
        m += 1
    return out[:m].copy()


def cast_scan(sensor: SensorConfig, directions: np.ndarray, pose: np.ndarray, raycaster: Raycaster) -> np.ndarray:
    """Cast the scan from ``pose`` (sensor → world); (M,4) float32 sensor-frame points ``[x, y, z, REFLECTANCE]``.

    Misses are dropped (the original wrote them at the origin), as are hits outside ``[min_range, max_range]``
    (planar depth ``t * d_x`` or Euclidean ``t * |d|``, per ``SensorConfig.range_mode``) and outside the
    ``z_min < z < z_max`` crop. ``directions`` (R,3) float64 sensor frame (``scan_directions``).
    """
    R, p = pose[:3, :3], pose[:3, 3]
    t, face = raycaster.cast(p, rotate_vectors(directions, R))
    z_min = -np.inf if sensor.z_min is None else sensor.z_min
    z_max = np.inf if sensor.z_max is None else sensor.z_max
    return _scan_points(t, face, np.ascontiguousarray(directions, dtype=np.float64), sensor.range_mode == "planar",
                        float(sensor.min_range), float(sensor.max_range), float(z_min), float(z_max), REFLECTANCE)


def warm_up(sensor: SensorConfig) -> None:
    """Load (or compile) the compiled kernels a frame uses, in this process, on tiny inputs of the real types.

    ``generate`` calls it before forking its workers, which then inherit the machine code instead of each loading
    it again (about 0.4 s per process, numba's start-up included).
    """
    camera = sensor.camera
    mask = np.zeros((camera.height, camera.width), dtype=bool)
    mask[camera.height // 2, camera.width // 2] = True
    tri = make_raycaster(np.array([[1.0, -1, -1], [1, 1, -1], [1, 0, 1]]), np.array([[0, 1, 2]]), "embree")
    cast_pixels(mask, camera, np.eye(4), tri, np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64))
    cast_scan(sensor, np.array([[1.0, 0.0, 0.0]]), np.eye(4), tri)
    depth_image(np.zeros((1, 4), dtype=np.float32), camera_calib(camera), (camera.width, camera.height), 1.0)


def label_pose(ctx: HouseContext, sensor: SensorConfig, pose: np.ndarray) -> BoxDecisions:
    """Every filter but the scan-point one (:func:`mpchair.labels.select.decide_boxes`) for the class objects of
    ``ctx`` seen from ``pose`` (4,4) sensor → world."""
    return decide_boxes(ctx.class_boxes, ctx.class_objects, pose, ctx.raycaster, ctx.house.face_object, sensor.camera,
                        camera_calib(sensor.camera), sensor.filters, ctx.scenes, ctx.cover_boxes, ctx.outside)


def make_frame(ctx: HouseContext, settings: FrameSettings, index: int, directions: np.ndarray) -> FrameResult:
    """Frame ``index`` of ``ctx.house`` (see the module docstring); raises :class:`InputError` when no candidate in
    ``settings.max_attempts`` gives a valid viewpoint (or a kept box), saying how many valid viewpoints were found."""
    sensor = settings.sensor
    filters: LabelFilters = sensor.filters
    rng = frame_rng(settings.seed, ctx.house.id, index)
    views = 0
    rays = 0
    for vp in viewpoint_stream(rng, ctx.sampler, ctx.raycaster, ctx.floor_ok, ctx.normal_z, settings.viewpoints,
                               settings.max_attempts):
        views += 1
        pose = vp.pose()
        dec = label_pose(ctx, sensor, pose)
        rays += dec.dense_rays
        if not dec.kept.any() and not settings.keep_empty:
            continue
        points = cast_scan(sensor, directions, pose, ctx.raycaster)
        rays += len(directions)
        dec = apply_scan_points(dec, points, filters)
        if not dec.kept.any() and not settings.keep_empty:
            continue
        return FrameResult(vp, dec, points, views, rays)
    if views == 0:
        raise InputError(f"house {ctx.house.id}: found 0 valid viewpoints in {settings.max_attempts} attempts "
                         f"(frame {index}); {why_no_viewpoint(ctx, settings, index)}")
    raise InputError(f"house {ctx.house.id}: found {views} valid viewpoints in {settings.max_attempts} attempts "
                     f"(frame {index}) but none keeps a box; use --keep-empty, a higher --max-attempts or a house "
                     "with more objects")


#: Candidates :func:`why_no_viewpoint` examines at least (the default ``--max-attempts``).
DIAGNOSE_CANDIDATES = 400


def why_no_viewpoint(ctx: HouseContext, settings: FrameSettings, index: int) -> str:
    """Why frame ``index`` found no valid viewpoint: the attempt limit, or the check that failed every candidate.

    Draws the frame's own candidates again (the same generator and order as ``viewpoint_stream``), at least
    :data:`DIAGNOSE_CANDIDATES` of them, and validates them with each check of ``mpchair.scan.viewpoints`` added in
    turn: landing on the floor, headroom, clearance.
    """
    params = settings.viewpoints
    n = max(settings.max_attempts, DIAGNOSE_CANDIDATES)
    rng = frame_rng(settings.seed, ctx.house.id, index)
    cand = []
    for _ in range(n):
        cand.append(ctx.sampler.sample(rng))
        rng.random()  # the candidate's yaw
    xy = np.array([[c[1], c[2]] for c in cand])
    z = np.array([c[3] for c in cand])  # the spot's floor height (region or navmesh)

    def passing(p: ViewpointParams) -> int:
        return int(validate_candidates(xy, z, ctx.raycaster, ctx.floor_ok, ctx.normal_z, p)[0].sum())

    on_floor = passing(dataclasses.replace(params, robot_radius=0.0, head_margin=-np.inf))
    headroom = passing(dataclasses.replace(params, robot_radius=0.0))
    valid = passing(params)
    if valid:
        return (f"the attempt limit: {valid} of the frame's first {n} candidates are valid; raise --max-attempts "
                f"(now {settings.max_attempts})")
    if not on_floor:
        return (f"the floor: none of {n} candidates landed on a floor face within {params.drop_tolerance} m of its "
                "region's floor height (the house's floor polygons do not match its mesh)")
    if not headroom:
        return (f"headroom: of {on_floor} candidates on the floor of {n}, none has "
                f"{params.height + params.head_margin:g} m free above it; lower --height (now {params.height:g})")
    return (f"clearance: of {headroom} candidates on the floor with headroom, of {n}, none has {params.robot_radius:g} "
            "m free around it; lower --robot-radius")


def box_labels(decisions: BoxDecisions, idx: np.ndarray, names: list[str], calib: Calib,
               size: tuple[int, int]) -> Labels:
    """KITTI label rows of candidates ``idx`` (``names`` = KITTI type per candidate): 2D box = projection clipped to
    the image, truncation = fraction of the projected box outside it (both from ``mpchair.geometry``), occluded from
    the dense visible fraction (-1 where not computed), alpha / rotation_y from the box conversion."""
    boxes = decisions.boxes[idx]
    loc, dims, ry, alpha = boxes_to_kitti_camera(boxes, calib)
    bbox, trunc = project_boxes_to_image(boxes, calib, size)
    return Labels(np.array([names[i] for i in idx], dtype=str), trunc, decisions.occluded[idx], alpha, bbox, dims,
                  loc, ry)


def dontcare_candidates(decisions: BoxDecisions) -> np.ndarray:
    """Candidates rejected *inside* the labelled region (a reason not in
    :data:`~mpchair.labels.filters.OUTSIDE_REGION_REASONS`: too occluded, too few points, ...)."""
    return np.flatnonzero([r != "" and r not in OUTSIDE_REGION_REASONS for r in decisions.reasons]).astype(np.int64)


def frame_labels(decisions: BoxDecisions, names: list[str], calib: Calib, size: tuple[int, int],
                 dontcare: bool = False) -> Labels:
    """KITTI labels of the kept boxes (:func:`box_labels`); one DontCare row when there is no row at all.

    With ``dontcare``, each of the :func:`dontcare_candidates` becomes a DontCare row with its projected 2D box, so
    that a detection of it is not counted as a false positive (KITTI applies DontCare to 2D boxes only; see
    ``docs/streaming.md`` for 3D).
    """
    k = np.flatnonzero(decisions.kept)
    d = dontcare_candidates(decisions) if dontcare else np.zeros(0, dtype=np.int64)
    if len(k) == 0 and len(d) == 0:
        # OpenPCDet's info builder crashes on an empty label file: a DontCare row loads as zero boxes.
        return Labels(np.array([DONTCARE]), [-1.0], [-1], [-10.0], np.zeros((1, 4)), -np.ones((1, 3)),
                      np.full((1, 3), -1000.0), [-10.0])
    labels = box_labels(decisions, k, names, calib, size)
    if len(d) == 0:
        return labels
    dc_bbox, _ = project_boxes_to_image(decisions.boxes[d], calib, size)
    n = len(d)
    ignored = Labels(np.full(n, DONTCARE), np.full(n, -1.0), np.full(n, -1), np.full(n, -10.0), dc_bbox,
                     -np.ones((n, 3)), np.full((n, 3), -1000.0), np.full(n, -10.0))
    return Labels.concatenate([labels, ignored])


def _r(x: float, nd: int = 6) -> float | None:
    return None if not np.isfinite(x) else round(float(x), nd)


def frame_record(fid: str, house: House, index: int, result: FrameResult) -> FrameRecord:
    """The frame's manifest entry (no paths or times): house, pose, points, kept / rejected boxes (sensor frame)."""
    dec = result.decisions
    pose = result.viewpoint.pose()
    kept, rejected = [], []
    for j, obj in enumerate(dec.objects):
        o = house.objects[int(obj)]
        if dec.reasons[j] == "":
            kept.append(KeptBox(
                object_index=int(o.index), object_id=o.id, class_name=o.mpcat40_name,
                box=tuple(_r(v) for v in dec.boxes[j]),
                visible_pixels=int(dec.visible_pixels[j]),
                points_in_box=int(dec.points_in_box[j]),
                in_box_fraction=_r(dec.in_box_fraction[j]),
                # "lower_bound": the three counts above cover a coarse subset of the grid that already proves the
                # box passes (mpchair.labels.visibility); "exact": the whole grid region was cast.
                visibility="exact" if dec.exact[j] else "lower_bound",
                scan_points=int(dec.scan_points[j]),
                visible_fraction=_r(dec.visible_fraction[j]),
                occluded=int(dec.occluded[j]),
            ))
        else:
            measured = dec.visible_pixels[j] >= 0  # else a filter before the dense visibility rejected it
            rejected.append(RejectedBox(
                object_index=int(o.index), object_id=o.id, class_name=o.mpcat40_name, reason=dec.reasons[j],
                visible_pixels=int(dec.visible_pixels[j]) if measured else None,
                points_in_box=int(dec.points_in_box[j]) if measured else None,
            ))
    return FrameRecord(
        frame=fid,
        house=house.id,
        index=index,
        attempt=result.viewpoint.attempt,
        views_tried=result.views_tried,
        pose=tuple(tuple(_r(v, 9) for v in row) for row in pose[:3]),
        yaw=_r(result.viewpoint.yaw, 9),
        points=len(result.points),
        rays=result.rays,
        kept=tuple(kept),
        rejected=tuple(rejected),
    )


@functools.lru_cache(maxsize=4)
def calib_text(camera: CameraConfig) -> str:
    """The calib file of every frame of a camera (the same text each time: formatted once per process)."""
    return format_calib(camera_calib(camera))


def write_frame(out: Path, fid: str, house: House, index: int, result: FrameResult,
                sensor: SensorConfig) -> FrameRecord:
    """Write one frame's KITTI files (velodyne, label_2, calib, image_2, pose), then its record (``.frames/``, last:
    a record on disk means the whole frame is). Returns the record."""
    camera = sensor.camera
    calib = camera_calib(camera)
    size = (camera.width, camera.height)
    names = [kitti_name(house.objects[int(o)].mpcat40_name) for o in result.decisions.objects]
    paths = frame_paths(out, fid)
    write_velodyne(paths.velodyne, result.points)
    write_labels(paths.label_2, frame_labels(result.decisions, names, calib, size))
    write_text(paths.calib, calib_text(camera))
    write_bytes(paths.image_2, png_bytes(depth_image(result.points, calib, size, sensor.max_range)))
    pose = result.viewpoint.pose()
    write_text(out / "training" / "pose" / f"{fid}.txt", " ".join(f"{v:.9e}" for v in pose[:3].reshape(-1)) + "\n")
    record = frame_record(fid, house, index, result)
    write_text(record_path(out, fid), record.to_json() + "\n")
    return record


def record_path(out: Path, fid: str) -> Path:
    """Where the frame record of ``fid`` lives (``DIR/.frames/NNNNNN.json``)."""
    return Path(out) / ".frames" / f"{fid}.json"
