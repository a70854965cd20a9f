"""KITTI 3D object files, read and written exactly: ``calib`` (seven matrices, read by key, written in the order
OpenPCDet's line-index reader needs), ``label_2`` (15 columns, 16 with a score, DontCare rows last), ``velodyne``
(raw float32 x, y, z, reflectance), ``ImageSets`` (6-digit ids), the odometry sequence files (``times.txt``,
``poses.txt``) and the folder layout. Values stay in the file's own
frame (rectified camera for labels, LiDAR/sensor for scans); conversions to sensor boxes live in ``mpchair.geometry``.
Bad input raises :class:`mpchair.core.errors.InputError` naming the file and line; every write is atomic.
"""

from mpchair.kitti.calib import CALIB_KEYS, Calib, format_calib, read_calib, to_4x4, write_calib
from mpchair.kitti.imagesets import read_imageset, write_imageset
from mpchair.kitti.labels import DONTCARE, Labels, format_labels, parse_labels, read_labels, write_labels
from mpchair.kitti.layout import FramePaths, frame_paths, imageset_path, read_image_size
from mpchair.kitti.odometry import format_poses, format_times, read_poses, read_times, write_poses, write_times
from mpchair.kitti.velodyne import read_velodyne, velodyne_rows, write_velodyne

__all__ = [
    "CALIB_KEYS",
    "DONTCARE",
    "Calib",
    "FramePaths",
    "Labels",
    "format_calib",
    "format_labels",
    "parse_labels",
    "format_poses",
    "format_times",
    "frame_paths",
    "imageset_path",
    "read_calib",
    "read_image_size",
    "read_imageset",
    "read_labels",
    "read_poses",
    "read_times",
    "read_velodyne",
    "to_4x4",
    "velodyne_rows",
    "write_calib",
    "write_imageset",
    "write_labels",
    "write_poses",
    "write_times",
    "write_velodyne",
]
