"""Scanning a house mesh: sensor profiles (``mpchair/scan/profiles/*.yaml`` → :class:`SensorConfig`, their scan ray
patterns and the virtual camera's dense pixel grid), raycasting backends behind one :class:`Raycaster` protocol (Embree
through trimesh + embreex by default, Open3D's ``RaycastingScene`` as an alternative) and robot viewpoints sampled on
free floor (inside region floor polygons, or on habitat navmesh islands: ``navmesh.py``). Rays are in the sensor
frame (x forward, y left, z up, metres) until a pose moves them into the world frame (Matterport, z up, metres); hits
carry the face id that links them to objects and categories.
"""

from mpchair.scan.raycast import BACKENDS, EmbreeRaycaster, Open3DRaycaster, Raycaster, make_raycaster
from mpchair.scan.sensors import (
    CameraConfig,
    PinholePattern,
    SensorConfig,
    SpinningPattern,
    available_sensors,
    camera_calib,
    grid_directions,
    load_sensor,
    scan_directions,
)

__all__ = [
    "BACKENDS",
    "CameraConfig",
    "EmbreeRaycaster",
    "Open3DRaycaster",
    "PinholePattern",
    "Raycaster",
    "SensorConfig",
    "SpinningPattern",
    "available_sensors",
    "camera_calib",
    "grid_directions",
    "load_sensor",
    "make_raycaster",
    "scan_directions",
]
