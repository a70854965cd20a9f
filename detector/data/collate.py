"""Batching: samples keep their own point and box counts, so a batch is lists of per-sample tensors (no padding)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import torch

from detector.data.pipeline import Sample


@dataclasses.dataclass(frozen=True, eq=False)
class Batch:
    """B samples: ``points[b]`` (N_b,C) float32 and ``boxes[b]`` (M_b,7) float32 in the sensor frame (metres),
    ``labels[b]`` (M_b,) int64 class indices, ``frame_ids[b]`` the source frame ids."""

    frame_ids: tuple[str, ...]
    points: tuple[torch.Tensor, ...]
    boxes: tuple[torch.Tensor, ...]
    labels: tuple[torch.Tensor, ...]

    def __len__(self) -> int:
        return len(self.frame_ids)

    def to(self, device: torch.device | str, non_blocking: bool = False) -> Batch:
        """The same batch on ``device`` (``non_blocking``: overlap the copy from pinned memory with queued kernels)."""
        return Batch(
            self.frame_ids,
            tuple(p.to(device, non_blocking=non_blocking) for p in self.points),
            tuple(b.to(device, non_blocking=non_blocking) for b in self.boxes),
            tuple(l.to(device, non_blocking=non_blocking) for l in self.labels),
        )


def collate(samples: Sequence[Sample]) -> Batch:
    """Stack :class:`Sample` s into a :class:`Batch` (CPU tensors sharing the numpy memory where possible)."""
    return Batch(
        frame_ids=tuple(s.frame_id for s in samples),
        points=tuple(torch.from_numpy(s.points) for s in samples),
        boxes=tuple(torch.from_numpy(s.boxes) for s in samples),
        labels=tuple(torch.from_numpy(s.labels) for s in samples),
    )
