"""One training transform (GT sampling → flip → rotation → scaling → range filter → shuffle) and its dataset wrapper.

All randomness of sample ``index`` in epoch ``epoch`` comes from :func:`sample_rng` ``(seed, epoch, index)``: the same
sample gets the same augmentation whichever process, worker or rank builds it and whether or not the run was
resumed, which is what makes training reproducible and resumable.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from detector.data.augment import (
    filter_boxes_in_range,
    filter_points_in_range,
    global_rotation,
    global_scaling,
    random_flip_y,
    shuffle_points,
)
from detector.data.gt_database import GTDatabase, sample_ground_truth
from detector.data.kitti_dataset import Frame, KittiDataset


def sample_rng(seed: int, epoch: int, index: int) -> np.random.Generator:
    """The generator of sample ``index`` (position in the split) in epoch ``epoch`` of a run seeded ``seed``."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), int(epoch), int(index)])))


@dataclasses.dataclass(frozen=True)
class AugmentOptions:
    """What the training transform does (every step can be switched off).

    * ``point_cloud_range`` ``[x_min, y_min, z_min, x_max, y_max, z_max]`` metres, sensor frame: points outside are
      dropped (``min <= p < max``), boxes whose BEV centre is outside are dropped (``range_filter``).
    * ``num_point_features``: columns of the scan handed to the model (3 = xyz, 4 = xyz + reflectance).
    * ``gt_sampling`` with ``sample_counts`` / ``min_points`` as ``((class, n), ...)`` pairs: top each scene up to
      ``n`` objects of ``class`` from the GT database, using only objects with at least ``min_points`` points.
    * ``flip``: mirror ``y → -y`` with ``flip_probability``. ``rotation`` ``(lo, hi)`` radians: a uniform global
      rotation about +z. ``scaling`` ``(lo, hi)``: a uniform global scale factor. ``None`` switches either off.
    * ``shuffle``: shuffle the point order (the voxelizer keeps the first points of a full pillar).
    """

    point_cloud_range: tuple[float, float, float, float, float, float]
    num_point_features: int = 4
    range_filter: bool = True
    gt_sampling: bool = False
    sample_counts: tuple[tuple[str, int], ...] = ()
    min_points: tuple[tuple[str, int], ...] = ()
    flip: bool = False
    flip_probability: float = 0.5
    rotation: tuple[float, float] | None = None
    scaling: tuple[float, float] | None = None
    shuffle: bool = True


@dataclasses.dataclass(frozen=True, eq=False)
class Sample:
    """One model input: ``points`` (N,C) float32 sensor frame (metres), training ``boxes`` (M,7) float32 sensor frame,
    ``labels`` (M,) int64 class indices, and the ``frame_id`` it came from."""

    frame_id: str
    points: np.ndarray
    boxes: np.ndarray
    labels: np.ndarray


def make_training_sample(
    frame: Frame, options: AugmentOptions, rng: np.random.Generator, database: GTDatabase | None = None,
    classes: tuple[str, ...] = (),
) -> Sample:
    """Apply the training transform to ``frame`` with the randomness of ``rng`` (see :class:`AugmentOptions`).

    ``database`` and ``classes`` (training class names, index = label) are needed when ``options.gt_sampling`` is on.
    """
    points, boxes, labels = frame.points, frame.boxes, frame.labels
    if options.gt_sampling:
        if database is None:
            raise ValueError("gt_sampling needs a GT database")
        pasted = sample_ground_truth(
            points, boxes, labels, database=database, classes=classes, sample_counts=dict(options.sample_counts),
            min_points=dict(options.min_points), rng=rng, obstacles=frame.other_boxes,
        )
        points, boxes, labels = pasted.points, pasted.boxes, pasted.labels
    if options.flip:
        points, boxes, _ = random_flip_y(points, boxes, rng, options.flip_probability)
    if options.rotation is not None:
        points, boxes = global_rotation(points, boxes, float(rng.uniform(*options.rotation)))
    if options.scaling is not None:
        points, boxes = global_scaling(points, boxes, float(rng.uniform(*options.scaling)))
    if options.range_filter:
        points = filter_points_in_range(points, options.point_cloud_range)
        keep = filter_boxes_in_range(boxes, options.point_cloud_range)
        boxes, labels = boxes[keep], labels[keep]
    if options.shuffle:
        points = shuffle_points(points, rng)
    return Sample(
        frame_id=frame.frame_id,
        points=np.ascontiguousarray(points[:, : options.num_point_features], dtype=np.float32),
        boxes=np.ascontiguousarray(boxes, dtype=np.float32).reshape(-1, 7),
        labels=np.asarray(labels, dtype=np.int64),
    )


def make_eval_sample(frame: Frame, options: AugmentOptions) -> Sample:
    """The deterministic inference transform: range filter on points and feature columns only (no augmentation)."""
    points = filter_points_in_range(frame.points, options.point_cloud_range)
    return Sample(
        frame_id=frame.frame_id,
        points=np.ascontiguousarray(points[:, : options.num_point_features], dtype=np.float32),
        boxes=np.ascontiguousarray(frame.boxes, dtype=np.float32).reshape(-1, 7),
        labels=np.asarray(frame.labels, dtype=np.int64),
    )


class TrainingSet(torch.utils.data.Dataset):
    """Map-style dataset over keys ``(epoch, index)``: frame ``index`` of ``frames`` with that epoch's augmentation.

    Keys instead of plain indices let any sampler, worker or rank build exactly the sample a single process would.
    """

    def __init__(
        self,
        frames: KittiDataset,
        options: AugmentOptions,
        *,
        seed: int,
        database: GTDatabase | None = None,
    ) -> None:
        self.frames = frames
        self.options = options
        self.seed = int(seed)
        self.database = database

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, key: tuple[int, int]) -> Sample:
        epoch, index = key
        return self.sample(epoch, index, index)

    def sample(self, epoch: int, slot: int, frame_index: int) -> Sample:
        """Frame ``frame_index`` augmented with the generator ``(seed, epoch, slot)`` (``slot``: position in the
        epoch's sample sequence; equal to the frame index when an epoch is one ordered pass)."""
        frame = self.frames[frame_index]
        return make_training_sample(
            frame, self.options, sample_rng(self.seed, epoch, slot), self.database, self.frames.classes
        )
