"""What an experiment config asks of the data: the split reader and the training transform.

Shared by training (``detector.train``), inference (``detector.infer``) and the benchmarks (``detector.bench``), so
none of them imports another for it.
"""

from __future__ import annotations

from pathlib import Path

from detector.data import AugmentOptions, KittiDataset
from detector.models import ExperimentConfig


def augment_options(cfg: ExperimentConfig) -> AugmentOptions:
    """The training transform described by the experiment's ``data`` section (and the model's range / channels)."""
    d = cfg.data
    counts = tuple((c, d.gt_sampling.sample) for c in d.classes)
    minimum = tuple((c, d.gt_sampling.min_points) for c in d.classes)
    return AugmentOptions(
        point_cloud_range=cfg.model.point_cloud_range,
        num_point_features=cfg.model.in_channels,
        range_filter=d.range_filter,
        gt_sampling=d.gt_sampling.enabled,
        sample_counts=counts,
        min_points=minimum,
        flip=d.flip_y,
        rotation=d.rotation,
        scaling=d.scaling,
        shuffle=d.point_shuffle,
    )


def open_split(cfg: ExperimentConfig, data_dir: str | Path, split: str) -> KittiDataset:
    """The frames of ``split`` read as the experiment's ``data`` section says (classes, renames, FOV crop)."""
    return KittiDataset(
        data_dir, split, classes=cfg.data.classes, name_map=dict(cfg.data.rename), fov_crop=cfg.data.fov_crop
    )
