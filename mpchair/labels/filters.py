"""The box filters' thresholds (:class:`LabelFilters`, every field with its unit and reason) and reject reasons.

Defaults reproduce the original Matterport-Chair generator (``docs/generate.md``, "Filters"). Pixel counts refer to
the virtual camera's full-resolution pixel grid (1024 x 1024 for ``mp3d-depth90``), not to the sparse saved scan.
"""

from __future__ import annotations

# The dataclass lives with the sensor profiles (each profile's YAML carries its thresholds, in the units of its own
# camera grid and rays); it is re-exported here, where the filters are applied.
from mpchair.geometry.region import REGION_TESTS
from mpchair.scan.sensors import LabelFilters

__all__ = ["OUTSIDE_REGION_REASONS", "REJECT_REASONS", "LabelFilters"]


#: Reasons written to the manifest for a rejected box, in the order the filters are applied (first failure wins).
REJECT_REASONS: tuple[str, ...] = (
    "height",  # centre outside ±max_abs_dz of the sensor
    "distance",  # horizontal distance > max_distance
    "fov",  # centre outside the camera's horizontal field of view
    "visible_pixels",  # <= min_visible_pixels dense pixels of the object visible
    "points_in_box",  # < min_points_in_box visible points inside the box
    "in_box_fraction",  # < min_in_box_fraction of the visible points inside the box
    "scan_points",  # < min_scan_points saved-scan points inside the box
)

#: Reasons that put a box outside the labelled region (:mod:`mpchair.geometry.region`). A box rejected for any other
#: reason lies inside it: ``mpchair stream`` writes such boxes as DontCare (ignored) instead of dropping them.
OUTSIDE_REGION_REASONS: tuple[str, ...] = REGION_TESTS
