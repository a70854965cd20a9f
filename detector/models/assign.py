"""Anchor → ground-truth assignment with the reference's "nearest BEV" axis-aligned IoU (no rotated IoU in training).

IoU: wrap each yaw into [-pi/2, pi/2); if ``|yaw| > pi/4`` swap l and w; take the axis-aligned BEV rectangle
(x extent l, y extent w) and compute the ordinary IoU. Per sample, over all anchors:

- positive if max IoU >= ``pos_iou_thr``; negative if max IoU < ``neg_iou_thr``; ignored in between;
- low-quality matches: for every GT whose best IoU is >= ``neg_iou_thr`` (and > 0), every anchor whose IoU with that
  GT equals the best becomes positive and regresses toward **that** GT (the upstream Open3D-ML fix; SPP kept the
  anchor's own argmax GT). When several GTs force one anchor, the last GT wins, as in the reference's loop.

Anchors are shared by all classes; a positive takes its GT's class (identical to the reference's per-class
assignment for the single-class configs used here).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch

from detector.models.box_coder import encode_boxes, limit_period


class Targets(NamedTuple):
    """Training targets of a batch of B samples over A anchors per sample.

    labels: (B, A) int64 class index of positives (0 elsewhere). pos / neg: (B, A) bool (ignored = neither).
    reg: (B, A, 7) residuals of the assigned GT w.r.t. the anchor (:func:`encode_boxes`; 0 where not positive).
    dir: (B, A) int64 direction bin of the assigned GT yaw (0 where not positive).
    """

    labels: torch.Tensor
    pos: torch.Tensor
    neg: torch.Tensor
    reg: torch.Tensor
    dir: torch.Tensor


def nearest_bev(boxes: torch.Tensor) -> torch.Tensor:
    """(N, 7) boxes → (N, 4) axis-aligned BEV rectangles ``[x_min, y_min, x_max, y_max]`` (m) after the l/w swap."""
    yaw = limit_period(boxes[:, 6], 0.5, math.pi).abs()
    swap = yaw > math.pi / 4
    ex = torch.where(swap, boxes[:, 4], boxes[:, 3])  # extent along x
    ey = torch.where(swap, boxes[:, 3], boxes[:, 4])
    return torch.stack([boxes[:, 0] - ex / 2, boxes[:, 1] - ey / 2, boxes[:, 0] + ex / 2, boxes[:, 1] + ey / 2], dim=1)


def axis_aligned_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(N, 4), (M, 4) rectangles ``[x_min, y_min, x_max, y_max]`` → (N, M) IoU (0 for disjoint or empty)."""
    lt = torch.maximum(a[:, None, :2], b[None, :, :2])
    rb = torch.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = (rb - lt).clamp(min=0).prod(dim=2)
    area_a = (a[:, 2:] - a[:, :2]).prod(dim=1)
    area_b = (b[:, 2:] - b[:, :2]).prod(dim=1)
    union = area_a[:, None] + area_b[None, :] - inter
    return torch.where(union > 0, inter / union.clamp(min=1e-12), torch.zeros_like(inter))


def direction_bin(yaw: torch.Tensor, dir_offset: float = 0.0) -> torch.Tensor:
    """Two-bin heading class: ``floor(wrap(yaw - dir_offset, [0, 2pi)) / pi)`` → 0 or 1 (int64)."""
    rot = limit_period(yaw - dir_offset, 0.0, 2 * math.pi)
    return torch.floor(rot / math.pi).long().clamp(0, 1)


def assign_sample(
    anchors: torch.Tensor,
    gt_boxes: torch.Tensor,
    gt_labels: torch.Tensor,
    *,
    pos_iou_thr: float,
    neg_iou_thr: float,
    dir_offset: float = 0.0,
) -> Targets:
    """One sample. anchors (A, 7), gt_boxes (M, 7) sensor frame, gt_labels (M,) int64 class indices → Targets with a
    leading batch dimension of 1."""
    a = anchors.shape[0]
    device = anchors.device
    labels = torch.zeros(a, dtype=torch.int64, device=device)
    reg = anchors.new_zeros((a, 7))
    dirs = torch.zeros(a, dtype=torch.int64, device=device)
    if gt_boxes.shape[0] == 0:
        pos = torch.zeros(a, dtype=torch.bool, device=device)
        return Targets(labels[None], pos[None], (~pos)[None], reg[None], dirs[None])
    gt_boxes = gt_boxes.to(anchors.dtype)
    iou = axis_aligned_iou(nearest_bev(anchors), nearest_bev(gt_boxes))  # (A, M)
    max_iou, assigned = iou.max(dim=1)
    pos = max_iou >= pos_iou_thr
    neg = max_iou < neg_iou_thr
    gt_best = iou.max(dim=0).values  # (M,)
    eligible = (gt_best >= neg_iou_thr) & (gt_best > 0)
    forced = (iou == gt_best[None, :]) & eligible[None, :]  # (A, M)
    m = gt_boxes.shape[0]
    # Last forcing GT per anchor (1-based so that 0 means "not forced").
    last = (forced.long() * torch.arange(1, m + 1, device=device)[None, :]).max(dim=1).values
    is_forced = last > 0
    assigned = torch.where(is_forced, last - 1, assigned)
    pos = pos | is_forced
    neg = neg & ~pos
    idx = torch.nonzero(pos).squeeze(1)
    matched = gt_boxes[assigned[idx]]
    labels[idx] = gt_labels.to(device=device, dtype=torch.int64)[assigned[idx]]
    reg[idx] = encode_boxes(matched, anchors[idx])
    dirs[idx] = direction_bin(matched[:, 6], dir_offset)
    return Targets(labels[None], pos[None], neg[None], reg[None], dirs[None])


def assign_targets(
    anchors: torch.Tensor,
    gt_boxes_list: Sequence[torch.Tensor],
    gt_labels_list: Sequence[torch.Tensor],
    *,
    pos_iou_thr: float,
    neg_iou_thr: float,
    dir_offset: float = 0.0,
) -> Targets:
    """Batch of B samples: anchors (A, 7) shared; gt_boxes_list[b] (M_b, 7) sensor frame (m, rad); gt_labels_list[b]
    (M_b,) int64 → :class:`Targets` with shapes (B, A[, 7])."""
    if len(gt_boxes_list) != len(gt_labels_list):
        raise ValueError("assign_targets: gt_boxes_list and gt_labels_list differ in length")
    parts = [
        assign_sample(
            anchors, b.to(anchors.device), l, pos_iou_thr=pos_iou_thr, neg_iou_thr=neg_iou_thr, dir_offset=dir_offset
        )
        for b, l in zip(gt_boxes_list, gt_labels_list)
    ]
    return Targets(*(torch.cat(t) for t in zip(*parts)))
