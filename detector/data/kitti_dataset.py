"""Read KITTI-format frames (mpchair output or real KITTI) into sensor-frame points and boxes.

A frame's labels live in the rectified camera frame (bottom centre, ``h w l``, ``rotation_y``); they are converted to
``(M, 7)`` sensor-frame boxes ``[x, y, z, l, w, h, yaw]`` (geometric centre, yaw CCW about +z) through that frame's
own calib with :func:`mpchair.geometry.labels_to_boxes`. Nothing here assumes mpchair's calibration: real KITTI frames
(tilted ``Tr_velo_to_cam``, per-frame image sizes) go through the same code.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from mpchair.core.errors import InputError
from mpchair.geometry import fov_mask, labels_to_boxes
from mpchair.kitti import (
    Calib,
    Labels,
    frame_paths,
    imageset_path,
    read_calib,
    read_image_size,
    read_imageset,
    read_labels,
    read_velodyne,
    velodyne_rows,
)


@dataclasses.dataclass(frozen=True, eq=False)
class Frame:
    """One frame as read from disk.

    * ``points`` (N,4) float32: ``x, y, z, reflectance`` in the sensor/LiDAR frame (metres), FOV-cropped if asked.
    * ``boxes`` (M,7) float64: training objects in the sensor frame (only rows whose mapped name is in ``classes``;
      never DontCare). ``labels`` (M,) int64 index into ``classes``; ``names`` (M,) the mapped class names.
    * ``other_boxes`` (K,7) float64: sensor-frame boxes of the remaining non-DontCare objects (other classes);
      GT sampling keeps clear of them.
    * ``gt`` the frame's label file as read (every row, DontCare included, raw names): what evaluation compares
      against. ``Labels.empty()`` when the frame has no label file (``testing/``).
    * ``calib`` the frame's calibration; ``image_size`` ``(W, H)`` pixels of its ``image_2`` (``None`` when not read).
    """

    frame_id: str
    points: np.ndarray
    boxes: np.ndarray
    labels: np.ndarray
    names: np.ndarray
    other_boxes: np.ndarray
    gt: Labels
    calib: Calib
    image_size: tuple[int, int] | None


def map_names(names: np.ndarray, name_map: Mapping[str, str] | None) -> np.ndarray:
    """Rename label types through ``name_map`` (e.g. ``{"Van": "Car"}``); names not in the map are kept."""
    if not name_map:
        return np.asarray(names, dtype=str)
    return np.array([name_map.get(str(n), str(n)) for n in names], dtype=str)


def load_frame(
    root: str | Path,
    frame_id: str,
    *,
    classes: Sequence[str],
    name_map: Mapping[str, str] | None = None,
    fov_crop: bool = True,
    split_dir: str = "training",
    with_labels: bool = True,
) -> Frame:
    """Read one frame of the KITTI folder ``root``.

    ``classes`` are the training class names (target index = position); label types are first renamed through
    ``name_map``, then rows whose name is not in ``classes`` (DontCare, other classes) are dropped from the training
    boxes but kept in ``Frame.gt``. With ``fov_crop`` only points in front of camera 0 that project inside this
    frame's real ``image_2`` size (read from the PNG header) are kept, as KITTI labels exist only there. Missing or
    malformed files raise :class:`InputError` naming the file.
    """
    paths = frame_paths(root, frame_id, split_dir=split_dir)
    points = read_velodyne(paths.velodyne)
    calib = read_calib(paths.calib)
    image_size = None
    if fov_crop:
        image_size = read_image_size(paths.image_2)
        points = points[fov_mask(points, calib, image_size)]
    gt = read_labels(paths.label_2) if with_labels else Labels.empty()
    objects = gt.objects()
    names = map_names(objects.names, name_map)
    keep = np.isin(names, list(classes))
    others = objects[~keep]
    others = others[np.all(others.dims_hwl > 0, axis=1)]  # a box-less row of another class is no obstacle
    objects, names = objects[keep], names[keep]
    if len(objects) and not np.all(objects.dims_hwl > 0):
        raise InputError("an object has a non-positive dimension (h, w, l must be > 0)", paths.label_2)
    boxes = labels_to_boxes(objects, calib) if len(objects) else np.zeros((0, 7))
    other_boxes = labels_to_boxes(others, calib) if len(others) else np.zeros((0, 7))
    class_index = {c: i for i, c in enumerate(classes)}
    labels = np.array([class_index[str(n)] for n in names], dtype=np.int64)
    return Frame(
        frame_id=str(frame_id),
        points=np.ascontiguousarray(points, dtype=np.float32),
        boxes=np.asarray(boxes, dtype=np.float64).reshape(-1, 7),
        labels=labels,
        names=names,
        other_boxes=np.asarray(other_boxes, dtype=np.float64).reshape(-1, 7),
        gt=gt,
        calib=calib,
        image_size=image_size,
    )


class KittiDataset:
    """The frames of one split (``ImageSets/<split>.txt``) of a KITTI-format folder, read on access.

    ``dataset[i]`` is a :class:`Frame` (see :func:`load_frame` for the meaning of the keyword arguments). The frame
    files live under ``<root>/<split_dir>/`` (``training`` for train/val/test splits of mpchair output and of
    labelled KITTI).
    """

    def __init__(
        self,
        root: str | Path,
        split: str,
        *,
        classes: Sequence[str],
        name_map: Mapping[str, str] | None = None,
        fov_crop: bool = True,
        split_dir: str = "training",
        with_labels: bool = True,
    ) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise InputError("dataset folder not found", self.root)
        if not classes:
            raise InputError("at least one class name is needed")
        self.split = split
        self.ids: list[str] = read_imageset(imageset_path(self.root, split))
        if not self.ids:
            raise InputError(f"split {split!r} lists no frames", imageset_path(self.root, split))
        self.classes = tuple(classes)
        self.name_map = dict(name_map or {})
        self.fov_crop = fov_crop
        self.split_dir = split_dir
        self.with_labels = with_labels

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, index: int) -> Frame:
        return self.load(self.ids[index])

    def check(self) -> None:
        """Parse every frame's calib and label file, check its scan's size and (with ``fov_crop``) its image header,
        without reading the scans: a missing or malformed file is an :class:`InputError` naming it. Runs check their
        splits this way before they write anything."""
        for fid in self.ids:
            paths = frame_paths(self.root, fid, split_dir=self.split_dir)
            velodyne_rows(paths.velodyne)
            read_calib(paths.calib)
            if self.fov_crop:
                read_image_size(paths.image_2)
            if self.with_labels:
                read_labels(paths.label_2)

    def load(self, frame_id: str) -> Frame:
        """The frame with id ``frame_id`` (6 digits), read with this dataset's options."""
        return load_frame(
            self.root,
            frame_id,
            classes=self.classes,
            name_map=self.name_map,
            fov_crop=self.fov_crop,
            split_dir=self.split_dir,
            with_labels=self.with_labels,
        )
