"""Labels of one frame: each object's vertically aligned yaw-only box (from the Matterport reader) moved into the
sensor frame (x forward, y left, z up, metres), then filtered like the original generator — centre height, distance,
camera field of view, dense visibility on the virtual camera's full-resolution grid (cast only inside the candidates'
projected boxes), points in box, in-box fraction, and optionally points of the saved scan. ``filters`` holds the
thresholds (one frozen dataclass, with units and reasons), ``visibility`` the dense casting, ``select`` the decisions.
"""

from mpchair.labels.filters import OUTSIDE_REGION_REASONS, REJECT_REASONS, LabelFilters
from mpchair.labels.select import (
    BoxDecisions,
    apply_scan_points,
    boxes_to_sensor,
    centre_reasons,
    decide_boxes,
    label_half_fov,
    occlusion_level,
)
from mpchair.labels.visibility import DenseHits, ObjectScenes, cast_dense, grid_regions, object_visibility

__all__ = [
    "OUTSIDE_REGION_REASONS",
    "REJECT_REASONS",
    "BoxDecisions",
    "DenseHits",
    "LabelFilters",
    "ObjectScenes",
    "apply_scan_points",
    "boxes_to_sensor",
    "cast_dense",
    "centre_reasons",
    "decide_boxes",
    "grid_regions",
    "label_half_fov",
    "object_visibility",
    "occlusion_level",
]
