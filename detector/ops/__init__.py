"""Exact rotated-box overlap ops for the detector and its evaluator: BEV intersection areas and IoUs of yaw-only
boxes by a float64 convex polygon clip (Sutherland–Hodgman, numba), 3D IoU, their KITTI camera-frame variants used
by the evaluator, and greedy rotated NMS. Boxes are ``(N, 7)`` ``[x, y, z, l, w, h, yaw]`` in the sensor frame
(x forward, y left, z up, metres; ``(x, y, z)`` the geometric centre, yaw CCW about +z from +x) unless a function says
camera frame. Identical boxes score exactly 1.0.
"""

from detector.ops.iou import (
    bev_intersection_area,
    bev_intersection_pairs,
    camera_boxes,
    camera_overlaps_indexed,
    camera_to_sensor_style,
    iou_3d,
    iou_3d_camera,
    iou_3d_camera_pairs,
    iou_3d_pairs,
    rotated_iou_bev,
    rotated_iou_bev_camera,
    rotated_iou_bev_camera_pairs,
    rotated_iou_bev_pairs,
)
from detector.ops.nms import rotated_nms

__all__ = [
    "bev_intersection_area",
    "bev_intersection_pairs",
    "camera_boxes",
    "camera_overlaps_indexed",
    "camera_to_sensor_style",
    "iou_3d",
    "iou_3d_camera",
    "iou_3d_camera_pairs",
    "iou_3d_pairs",
    "rotated_iou_bev",
    "rotated_iou_bev_camera",
    "rotated_iou_bev_camera_pairs",
    "rotated_iou_bev_pairs",
    "rotated_nms",
]
