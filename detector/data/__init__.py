"""The detector's data pipeline: KITTI-format folders (mpchair output or real KITTI) → training samples and batches.

``kitti_dataset`` reads one frame (scan, labels → sensor-frame boxes through the frame's calib, optional camera-FOV
crop, class filter and name mapping; the raw labels incl. DontCare are kept for evaluation). ``gt_database`` builds
the ground-truth object database and pastes sampled objects into scenes without BEV collisions. ``augment`` holds the
global augmentations (flip, rotation, scaling), the range filters and the point shuffle; ``pipeline`` chains them into
one training transform whose randomness comes only from a generator derived from ``(seed, epoch, sample index)``, so
runs are reproducible and resumable. ``collate`` batches samples as per-sample tensors (no padding).
"""

from detector.data.augment import (
    filter_boxes_in_range,
    filter_points_in_range,
    global_rotation,
    global_scaling,
    random_flip_y,
    shuffle_points,
)
from detector.data.collate import Batch, collate
from detector.data.gt_database import GTDatabase, bev_boxes_overlap, build_gt_database, sample_ground_truth
from detector.data.kitti_dataset import Frame, KittiDataset, load_frame
from detector.data.pipeline import AugmentOptions, Sample, TrainingSet, make_training_sample, sample_rng

__all__ = [
    "AugmentOptions",
    "Batch",
    "Frame",
    "GTDatabase",
    "KittiDataset",
    "Sample",
    "TrainingSet",
    "bev_boxes_overlap",
    "build_gt_database",
    "collate",
    "filter_boxes_in_range",
    "filter_points_in_range",
    "global_rotation",
    "global_scaling",
    "load_frame",
    "make_training_sample",
    "random_flip_y",
    "sample_ground_truth",
    "sample_rng",
    "shuffle_points",
]
