"""Dense PointPillars and the model parts Sparse PointPillars shares with it, assembled by one builder.

Stages in the order of the paper's timers: ``voxelizer`` (points → pillars, the project's one indexing rule),
``pillar_net`` (decorations + PointNet), ``scatter`` (dense pseudo-image), ``backbone`` / ``neck`` (SECOND + FPN;
``sparse_backbone`` holds the sparse twin), ``head`` (1x1 anchor head and its exact sparse twin), ``postprocess``
(top-k, decode, rotated NMS, direction fix); training parts ``anchors``, ``box_coder``, ``assign`` and ``losses``
(``Losses``); ``build`` (``build_model``, the one assembly from a :class:`detector.config.ModelConfig`; the experiment
schema itself lives in :mod:`detector.config`). Boxes everywhere are ``(N, 7) [x, y, z_centre, l, w, h, yaw]`` in the
sensor frame (x forward, y left, z up, metres), yaw CCW from +x.
"""

from detector.models.assign import Targets, assign_targets
from detector.models.build import build_model
from detector.models.head import HeadOutput
from detector.models.losses import Losses, compute_loss
from detector.models.pointpillars import PointPillars
from detector.models.postprocess import Detections

__all__ = [
    "Detections",
    "HeadOutput",
    "Losses",
    "PointPillars",
    "Targets",
    "assign_targets",
    "build_model",
    "compute_loss",
]
