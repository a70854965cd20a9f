"""Frames, boxes and pillars: the geometry both ``mpchair`` and ``detector`` share. Boxes are ``(N, 7)`` float64
``[x, y, z, l, w, h, yaw]`` (geometric centre, ``l`` along the heading, yaw CCW about +z from +x) in the sensor frame
(x forward, y left, z up, metres) unless a docstring says world frame (Matterport, z up, metres). ``frames`` holds
angle wrapping and rigid 4×4 transforms, ``boxes`` corners / BEV polygons / point membership, ``camera`` the
conversions to and from KITTI camera labels and image_2 projection, ``pillars`` the one pillar indexing rule and the
pseudoimage grid (``PseudoimageGeometry``, ``frame_density``), ``region`` the labelled region (box centre height,
distance, field of view). See ``docs/conventions.md``.
"""

from mpchair.geometry.boxes import bev_polygons, box_corners, points_in_boxes
from mpchair.geometry.camera import (
    BOX_EDGES,
    NEAR_PLANE,
    boxes_to_kitti_camera,
    fov_mask,
    kitti_camera_to_boxes,
    labels_to_boxes,
    project_boxes_to_image,
)
from mpchair.geometry.frames import (
    HABITAT_TO_MP3D,
    SENSOR_TO_CAMERA,
    canonical_yaw,
    habitat_to_mp3d,
    invert_rigid,
    make_tr_velo_to_cam,
    mp3d_to_habitat,
    rigid_from,
    rotate_vectors,
    transform_boxes,
    transform_points,
    wrap_angle,
    yaw_matrix,
    yaw_of,
)
from mpchair.geometry.pillars import (
    KITTI_GEOMETRY,
    MATTERPORT_GEOMETRY,
    PseudoimageGeometry,
    frame_density,
    geometry_from_model_yaml,
    grid_size,
    pillar_coords,
)
from mpchair.geometry.region import REGION_TESTS, in_region, region_failures

__all__ = [
    "BOX_EDGES",
    "KITTI_GEOMETRY",
    "MATTERPORT_GEOMETRY",
    "PseudoimageGeometry",
    "frame_density",
    "geometry_from_model_yaml",
    "HABITAT_TO_MP3D",
    "NEAR_PLANE",
    "REGION_TESTS",
    "SENSOR_TO_CAMERA",
    "bev_polygons",
    "box_corners",
    "canonical_yaw",
    "boxes_to_kitti_camera",
    "fov_mask",
    "grid_size",
    "habitat_to_mp3d",
    "in_region",
    "invert_rigid",
    "kitti_camera_to_boxes",
    "labels_to_boxes",
    "make_tr_velo_to_cam",
    "mp3d_to_habitat",
    "pillar_coords",
    "points_in_boxes",
    "project_boxes_to_image",
    "region_failures",
    "rigid_from",
    "transform_boxes",
    "rotate_vectors",
    "transform_points",
    "wrap_angle",
    "yaw_matrix",
    "yaw_of",
]
