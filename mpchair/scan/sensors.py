"""Sensor profiles: the scan's ray pattern, its range limits, and the virtual pinhole camera used for labels.

A profile is a YAML file (the shipped ones in ``mpchair/scan/profiles/``, package data) loaded into
:class:`SensorConfig`. Every direction here is in the sensor frame (x forward, y left, z up); lengths are metres,
angles degrees in configs and radians in code.

Two ray patterns:

* ``pinhole`` (``mp3d-depth90``, the paper's sensor): the virtual camera's pixel grid, of which every ``row_step``-th
  row is kept, flattened row-major, and every ``flat_step``-th ray kept. Pixel ``(r, c)`` of a W x H grid looks along
  ``(1, -u, v)`` with ``u = tan(hfov/2) * (-1 + 2c/(W-1))``, ``v = tan(vfov/2) * (1 - 2r/(H-1))`` (habitat's
  ``linspace(-1, 1, W)`` back-projection, mirrored into a right-handed frame). With ``x = 1`` the ray parameter ``t``
  at a hit *is* the planar depth.
* ``spinning`` (360° LiDARs): ``beams`` elevations evenly spaced from ``elevation_max_deg`` (row 0) down to
  ``elevation_min_deg``, ``columns`` azimuths ``2 pi k / columns`` CCW from +x; unit directions, so ``t`` is the
  Euclidean range.

The *virtual camera* (:class:`CameraConfig`) defines ``calib`` (``P2``) and ``image_2``, and its full-resolution pixel
grid is where the visibility filters are evaluated, for every profile (see ``docs/generate.md``).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Literal

import numpy as np

from mpchair.core.config import load_config, package_folder, packaged_names, resolve_named_file
from mpchair.core.errors import InputError
from mpchair.geometry import make_tr_velo_to_cam
from mpchair.kitti import Calib

#: Folder of the shipped sensor profiles (``mpchair/scan/profiles``, package data: also in an installed wheel).
SENSOR_DIR = package_folder("mpchair", "scan/profiles")


@dataclasses.dataclass(frozen=True)
class LabelFilters:
    """Thresholds deciding which object boxes become labels (all relative to the sensor frame).

    * ``max_abs_dz`` (m): keep a box only if its centre is within ``±max_abs_dz`` of the sensor height
      (original: -1 <= z <= 1). Reason: the robot sees objects near its own height; ceilings/upper floors are noise.
    * ``max_distance`` (m): horizontal distance sensor → box centre must be ``<= max_distance`` (original 7 m).
      Reason: beyond it a chair has too few points in the 21k-ray scan to be learnable.
    * ``fov`` (bool): box centre must lie inside the virtual camera's horizontal field of view (original: atan2(|y|, x)
      < 45 deg). Reason: KITTI labels exist only inside image_2, and OpenPCDet crops points to it.
    * ``min_visible_pixels`` (pixels, strict ``>``): the object must cover more than this many pixels of the dense
      camera grid, after occlusion (original: > 35 on 1024 x 1024). Reason: "highly occluded" objects are rejected.
    * ``min_points_in_box`` (pixels/points, ``>=``): at least this many of the object's visible dense-grid points
      must lie inside its aligned box (original 35). Reason: "too few points".
    * ``min_in_box_fraction`` (fraction, ``>=``): at least this fraction of the object's visible dense-grid points
      inside its box (original 0.8). Reason: holes / label noise push points of the object outside its box.
    * ``min_scan_points`` (points of the saved scan, ``>=``): points of the saved scan inside the box (0 = off, the
      original). Reason: the equivalent threshold on the profile's own rays, used by the 360° profiles.
    * ``occlusion_cutoffs`` (fractions): KITTI ``occluded`` is 0 when the visible fraction of the object's
      unoccluded silhouette is ``>= cutoffs[0]``, 1 when ``>= cutoffs[1]``, else 2. Reason: KITTI's 0/1/2 levels
      ("fully visible", "partly", "largely occluded") need a number; the devkit never defined one.
    * ``box_margin`` (m): each box side is enlarged by this much for the in-box counts. Reason: an object's surface
      lies *on* its box, and float rounding would put half of those hits just outside.
    """

    max_abs_dz: float = 1.0
    max_distance: float = 7.0
    fov: bool = True
    min_visible_pixels: int = 35
    min_points_in_box: int = 35
    min_in_box_fraction: float = 0.8
    min_scan_points: int = 0
    occlusion_cutoffs: tuple[float, float] = (0.8, 0.4)
    box_margin: float = 0.01

    def __post_init__(self) -> None:
        if self.max_abs_dz <= 0 or self.max_distance <= 0:
            raise ValueError("max_abs_dz and max_distance must be positive (metres)")
        if not 0.0 <= self.min_in_box_fraction <= 1.0:
            raise ValueError("min_in_box_fraction must be in [0, 1]")
        if min(self.min_visible_pixels, self.min_points_in_box, self.min_scan_points) < 0:
            raise ValueError("pixel / point thresholds must be >= 0")
        hi, lo = self.occlusion_cutoffs
        if not 0.0 <= lo <= hi <= 1.0:
            raise ValueError("occlusion_cutoffs must be (high, low) with 0 <= low <= high <= 1")



@dataclasses.dataclass(frozen=True)
class CameraConfig:
    """A virtual pinhole camera looking along sensor +x: image ``width`` x ``height`` pixels, fields of view in degrees.

    Its focal lengths are ``f_x = width / 2 / tan(hfov/2)``, ``f_y = height / 2 / tan(vfov/2)`` and its principal
    point the image centre ``(width/2, height/2)`` (KITTI's pixel-edge convention: ``mp3d-depth90`` gets f = 512,
    c = 512 on 1024 x 1024).
    """

    width: int = 1024
    height: int = 1024
    hfov_deg: float = 90.0
    vfov_deg: float = 90.0

    def __post_init__(self) -> None:
        if not (_whole(self.width) and _whole(self.height)) or self.width < 2 or self.height < 2:
            raise ValueError("camera width and height must be whole numbers >= 2 pixels")
        if not (0 < self.hfov_deg < 170 and 0 < self.vfov_deg < 170):
            raise ValueError("camera fields of view must be in (0, 170) degrees")


@dataclasses.dataclass(frozen=True)
class PinholePattern:
    """Scan rays taken from the camera grid: every ``row_step``-th row, flattened row-major, every ``flat_step``-th."""

    row_step: int = 10
    flat_step: int = 5

    def __post_init__(self) -> None:
        if not (_whole(self.row_step) and _whole(self.flat_step) and self.row_step >= 1 and self.flat_step >= 1):
            raise ValueError(f"pinhole: row_step and flat_step must be whole numbers >= 1, got {self.row_step!r} and "
                             f"{self.flat_step!r}")


@dataclasses.dataclass(frozen=True)
class SpinningPattern:
    """A 360° spinning LiDAR: ``beams`` x ``columns`` rays, elevations in degrees (max = row 0)."""

    beams: int
    columns: int
    elevation_min_deg: float
    elevation_max_deg: float

    def __post_init__(self) -> None:
        if not (_whole(self.beams) and _whole(self.columns) and self.beams >= 1 and self.columns >= 1):
            raise ValueError(f"spinning: beams and columns must be whole numbers >= 1, got {self.beams!r} and "
                             f"{self.columns!r}")
        if not (-90 <= self.elevation_min_deg <= self.elevation_max_deg <= 90):
            raise ValueError("spinning: need -90 <= elevation_min_deg <= elevation_max_deg <= 90 (degrees)")


@dataclasses.dataclass(frozen=True)
class SensorConfig:
    """One sensor profile (``mpchair/scan/profiles/<name>.yaml``, or a YAML file of the user's).

    ``range_mode`` says what ``min_range`` / ``max_range`` (metres) limit: ``planar`` depth along +x (a depth camera)
    or ``euclidean`` range (a LiDAR). Hits outside the limits are dropped, as are rays that hit nothing (the
    original put those at the origin). ``z_min`` / ``z_max`` (metres, relative to the sensor, exclusive) crop the saved
    points, ``None`` = no crop. ``filters`` holds the label thresholds (:class:`LabelFilters`).
    """

    name: str
    description: str
    pattern: Literal["pinhole", "spinning"]
    range_mode: Literal["planar", "euclidean"]
    max_range: float
    camera: CameraConfig
    min_range: float = 0.0
    pinhole: PinholePattern | None = None
    spinning: SpinningPattern | None = None
    z_min: float | None = None
    z_max: float | None = None
    filters: LabelFilters = LabelFilters()

    def __post_init__(self) -> None:
        if self.pattern == "pinhole" and self.pinhole is None:
            raise ValueError("pattern 'pinhole' needs a 'pinhole' block")
        if self.pattern == "spinning" and self.spinning is None:
            raise ValueError("pattern 'spinning' needs a 'spinning' block")
        if not 0 <= self.min_range < self.max_range:
            raise ValueError("need 0 <= min_range < max_range")


def _whole(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


#: Bytes one scan ray costs while a frame is made (directions, hits, primitive ids, points, label masks; measured:
#: a 100,000-beam pattern of 10^8 rays peaked at 16.9 GB), and one camera pixel (the image and its depth / id maps).
BYTES_PER_RAY = 170
BYTES_PER_PIXEL = 32


def scan_rays(sensor: SensorConfig) -> int:
    """How many rays one scan of ``sensor`` casts (before range limits drop any)."""
    if sensor.pattern == "spinning":
        return sensor.spinning.beams * sensor.spinning.columns
    cam, pin = sensor.camera, sensor.pinhole
    rows = -(-cam.height // pin.row_step)
    return -(-(rows * cam.width) // pin.flat_step)


def check_sensor_memory(sensor: SensorConfig, path: str | Path) -> None:
    """:class:`InputError` naming ``path`` when one frame of ``sensor`` needs more memory than this machine has (a
    lower bound: :data:`BYTES_PER_RAY` per ray and :data:`BYTES_PER_PIXEL` per camera pixel), before anything is
    allocated."""
    from mpchair.core.limits import machine_memory_bytes

    rays, pixels = scan_rays(sensor), sensor.camera.width * sensor.camera.height
    need, have = rays * BYTES_PER_RAY + pixels * BYTES_PER_PIXEL, machine_memory_bytes()
    if need > have:
        raise InputError(f"one scan needs at least {need / 2**30:,.1f} GiB ({rays:,} rays, a {sensor.camera.width:,} x "
                         f"{sensor.camera.height:,} camera) but this machine has {have / 2**30:,.1f} GiB; use fewer "
                         "beams / columns or a larger row_step, or a smaller camera", path)


def available_sensors(sensor_dir: Path = SENSOR_DIR) -> list[str]:
    """Names of the shipped sensor profiles (YAML file stems), sorted."""
    return packaged_names(sensor_dir)


def load_sensor(name_or_path: str | Path, sensor_dir: Path = SENSOR_DIR) -> SensorConfig:
    """Load a sensor profile by path to a YAML file or by packaged name (``mp3d-depth90``); an existing file wins.

    An unknown name is an :class:`InputError` listing the available profiles; a malformed file names the file.
    """
    p = resolve_named_file(name_or_path, sensor_dir, "sensor")
    try:
        sensor = load_config(SensorConfig, p)
    except ValueError as e:  # __post_init__ consistency checks
        raise InputError(str(e), p) from None
    check_sensor_memory(sensor, p)
    return sensor


def camera_intrinsics(camera: CameraConfig) -> tuple[float, float, float, float]:
    """``(f_x, f_y, c_x, c_y)`` in pixels of the virtual camera (principal point at the image centre)."""
    # Rounded to 1e-9 px so that 90 deg gives exactly 512 (tan(pi/4) is 0.9999999999999999 in floating point).
    fx = round(camera.width / 2.0 / math.tan(math.radians(camera.hfov_deg) / 2.0), 9)
    fy = round(camera.height / 2.0 / math.tan(math.radians(camera.vfov_deg) / 2.0), 9)
    return fx, fy, camera.width / 2.0, camera.height / 2.0


def camera_calib(camera: CameraConfig) -> Calib:
    """The KITTI calibration of the virtual camera: ``P0..P3`` = ``K [I | 0]``, ``R0_rect`` = I,
    ``Tr_velo_to_cam`` = the sensor → camera axis swap (no translation: the camera sits at the sensor origin),
    ``Tr_imu_to_velo`` = ``[I | 0]``.
    """
    fx, fy, cx, cy = camera_intrinsics(camera)
    P = np.array([[fx, 0.0, cx, 0.0], [0.0, fy, cy, 0.0], [0.0, 0.0, 1.0, 0.0]])
    eye34 = np.hstack([np.eye(3), np.zeros((3, 1))])
    return Calib(P0=P, P1=P, P2=P, P3=P, R0_rect=np.eye(3), Tr_velo_to_cam=make_tr_velo_to_cam(), Tr_imu_to_velo=eye34)


def grid_directions(camera: CameraConfig, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(N,3) float64 sensor-frame ray directions ``(1, -u, v)`` of camera-grid pixels ``(rows[i], cols[i])``.

    Unnormalised on purpose: the ray parameter of a hit is the planar depth (metres along +x).
    """
    rows = np.asarray(rows, dtype=np.float64)
    cols = np.asarray(cols, dtype=np.float64)
    tx = math.tan(math.radians(camera.hfov_deg) / 2.0)
    ty = math.tan(math.radians(camera.vfov_deg) / 2.0)
    d = np.empty((rows.size, 3))
    d[:, 0] = 1.0
    d[:, 1] = -tx * (-1.0 + 2.0 * cols.reshape(-1) / (camera.width - 1))
    d[:, 2] = ty * (1.0 - 2.0 * rows.reshape(-1) / (camera.height - 1))
    return d


def grid_pixels_of(camera: CameraConfig, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`grid_directions`: fractional grid ``(rows, cols)`` of sensor-frame directions with x > 0."""
    d = np.asarray(directions, dtype=np.float64)
    tx = math.tan(math.radians(camera.hfov_deg) / 2.0)
    ty = math.tan(math.radians(camera.vfov_deg) / 2.0)
    cols = (-d[:, 1] / d[:, 0] / tx + 1.0) * (camera.width - 1) / 2.0
    rows = (1.0 - d[:, 2] / d[:, 0] / ty) * (camera.height - 1) / 2.0
    return rows, cols


def scan_directions(sensor: SensorConfig) -> np.ndarray:
    """(R,3) float64 sensor-frame directions of one scan, in the profile's fixed order (R = 21,095 for mp3d-depth90).

    ``pinhole``: unnormalised camera-grid directions (``t`` = planar depth). ``spinning``: unit vectors, row-major over
    beams (top first) then azimuth.
    """
    if sensor.pattern == "pinhole":
        cam, pat = sensor.camera, sensor.pinhole
        rows = np.arange(0, cam.height, pat.row_step)
        rr = np.repeat(rows, cam.width)[:: pat.flat_step]
        cc = np.tile(np.arange(cam.width), len(rows))[:: pat.flat_step]
        return grid_directions(cam, rr, cc)
    sp = sensor.spinning
    el = np.radians(np.linspace(sp.elevation_max_deg, sp.elevation_min_deg, sp.beams))
    az = 2.0 * np.pi * np.arange(sp.columns) / sp.columns
    el, az = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)
    return d.reshape(-1, 3)
