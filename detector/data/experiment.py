"""What an experiment config asks of the data: the split reader, the training transform and inference-ready frames.

Shared by training (``detector.train``), inference (``detector.infer``), the benchmarks (``detector.bench``), the op
counts, the sparsity figures and streaming, so none of them imports another for it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from detector.config import ExperimentConfig
from detector.data.kitti_dataset import KittiDataset
from detector.data.pipeline import AugmentOptions, make_eval_sample
from mpchair.core.errors import InputError


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


@dataclass(frozen=True)
class EvalFrame:
    """One frame ready for inference: ``points`` (N, C) float32, sensor frame (m), range-filtered for the model."""

    frame_id: str
    points: np.ndarray


def load_eval_frames(
    cfg: ExperimentConfig, data_dir: str | Path, split: str, limit: int | None = None, start: int = 0, *,
    progress: bool = False,
) -> list[EvalFrame]:
    """Frames ``start .. start+limit`` of ``split`` of a KITTI-format folder, transformed as at inference
    (:func:`detector.data.pipeline.make_eval_sample`: range filter, ``in_channels`` columns); ``progress``: a bar on
    stderr when it is a terminal."""
    frames = open_split(cfg, data_dir, split)
    ids = frames.ids[start:] if limit is None else frames.ids[start : start + limit]
    if not ids:
        raise InputError(f"split {split!r} has no frame at index {start} (it has {len(frames.ids)})", data_dir)
    options = augment_options(cfg)
    bar = tqdm(ids, desc="loading frames", unit="frame", disable=None if progress else True, leave=False)
    return [EvalFrame(fid, make_eval_sample(frames.load(fid), options).points) for fid in bar]
