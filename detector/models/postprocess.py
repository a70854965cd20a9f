"""Head maps → detections (the paper's "BBox Extract" timer), Open3D-ML ``Anchor3DHead.get_bboxes`` semantics.

Per sample: keep the top ``nms_pre`` anchors by their max class score over the whole map (:func:`select_candidates`:
only anchors that can pass the score threshold compete, which selects the same anchors); decode; per class, keep
scores > ``score_thr`` and run greedy rotated BEV NMS (``detector.ops.rotated_nms``, IoU ``nms_iou``); then the
direction fix ``yaw = wrap(yaw - dir_offset, dir_limit_offset, pi) + dir_offset + pi * bin``.
With the reference's values (limit offset 0, as OpenPCDet/mmdet3d; SPP used 1, which turns every decoded heading pi
away from the GT direction) the output yaw lies in [0, 2pi). Detections are sorted by descending score.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from detector.models.box_coder import decode_boxes, limit_period
from detector.ops import rotated_nms


class Detections(NamedTuple):
    """One sample's detections: boxes (M, 7) ``[x, y, z_centre, l, w, h, yaw]`` sensor frame (m, rad CCW), scores
    (M,) in (score_thr, 1], labels (M,) int64 class indices."""

    boxes: torch.Tensor
    scores: torch.Tensor
    labels: torch.Tensor


def anchor_rows(m: torch.Tensor, idx: torch.Tensor, size: int) -> torch.Tensor:
    """One sample's (H, W, A*size) head map and anchor indices (k,) (anchor ``(iy * W + ix) * A + a``) → (k, size).

    Gathers the k rows from a view of the map: the head's maps are channel slices of one (H, W, O) output, which
    ``reshape(-1, size)`` would first copy whole (5.5 MB for the Matterport reg map).
    """
    cells = m.flatten(0, 1).unflatten(1, (-1, size))  # (H*W, A, size), a view for channel slices
    a = cells.shape[1]
    return cells[torch.div(idx, a, rounding_mode="floor"), idx % a]


def select_candidates(
    cls: torch.Tensor, *, num_classes: int, nms_pre: int, score_thr: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """One sample's (H, W, A*K) class-logit map → the anchors NMS can keep: indices (k,) (anchor ``(iy * W + ix) * A
    + a``) and sigmoid scores (k, K), highest max-class logit first (ties in anchor order), k <= ``nms_pre``.

    The same anchors as "top ``nms_pre`` by max class score, then score > ``score_thr``" (Open3D-ML's order), except
    that an anchor whose best score is at most ``score_thr`` is dropped before the top-k rather than after: it could
    not pass the score test anyway, and an anchor above it ranks the same with or without the anchors below. So the
    full map is read once, by a comparison of logits against ``logit(score_thr)`` (sigmoid is monotonic; the cut sits
    0.05 lower so no rounding of a bf16 sigmoid can drop an anchor the score test keeps), instead of a sigmoid, a max
    and a top-k over every anchor (0.2 M on the Matterport map, 3x the time). Candidate sets are a few hundred
    anchors at most on trained models; a sparse map's many equal bias scores reach the top-k only if they pass the
    cut, and then equal maps still select equal anchors.
    """
    _, w, ak = cls.shape
    per = cls.unflatten(-1, (ak // num_classes, num_classes))  # (H, W, A, K), a view
    best = per[..., 0] if num_classes == 1 else per.amax(dim=-1)  # (H, W, A) max class logit
    if score_thr <= 0:
        cut = -math.inf
    elif score_thr >= 1:
        cut = math.inf
    else:
        cut = math.log(score_thr / (1 - score_thr)) - 0.05
    # Two passes, both cheap: the max of every image row (one contiguous read), then the few rows that hold a
    # candidate. One nonzero over the whole map took 4x as long (0.4 ms on the Matterport map).
    rows = torch.nonzero(best.amax(dim=(1, 2)) > cut).squeeze(1)
    ry, ix, ia = torch.nonzero(best[rows] > cut, as_tuple=True)  # row-major, so anchor indices ascend
    iy = rows[ry]
    idx = (iy * w + ix) * per.shape[2] + ia
    logit = best[iy, ix, ia]
    if idx.numel() > nms_pre:
        keep = torch.topk(logit, nms_pre).indices
        idx, logit = idx[keep], logit[keep]
    idx = idx[torch.argsort(logit, descending=True, stable=True)]
    return idx, torch.sigmoid(anchor_rows(cls, idx, num_classes))


@torch.no_grad()
def postprocess(
    cls: torch.Tensor,
    reg: torch.Tensor,
    dir: torch.Tensor,
    anchors: torch.Tensor,
    *,
    num_classes: int,
    nms_pre: int = 100,
    score_thr: float = 0.1,
    nms_iou: float = 0.01,
    dir_offset: float = 0.0,
    dir_limit_offset: float = 0.0,
) -> list[Detections]:
    """cls (B, H, W, A*K), reg (B, H, W, A*7), dir (B, H, W, A*2) head maps and anchors (H*W*A, 7) → B detections.

    The maps may have any strides (the head's inference output is channel-planar). Equal maps select equal anchors,
    ties included, so the dense head and the exact sparse head give the same detections. Runs without autograd.
    """
    b = cls.shape[0]
    predicted = math.prod(cls.shape[1:]) // num_classes
    if predicted != anchors.shape[0]:
        raise ValueError(f"postprocess: {predicted} predicted anchors but {anchors.shape[0]} anchors")
    out = []
    for i in range(b):
        top, scores = select_candidates(cls[i], num_classes=num_classes, nms_pre=nms_pre, score_thr=score_thr)
        boxes = decode_boxes(anchor_rows(reg[i], top, 7), anchors[top])
        dir_bin = anchor_rows(dir[i], top, 2).argmax(dim=1)
        keep_boxes, keep_scores, keep_labels = [], [], []
        for c in range(num_classes):
            mask = scores[:, c] > score_thr
            if not bool(mask.any()):
                continue
            idx = torch.nonzero(mask).squeeze(1)
            kept = idx[rotated_nms(boxes[idx], scores[idx, c], nms_iou)]
            bx = boxes[kept].clone()
            rot = limit_period(bx[:, 6] - dir_offset, dir_limit_offset, math.pi)
            bx[:, 6] = rot + dir_offset + math.pi * dir_bin[kept].to(bx.dtype)
            keep_boxes.append(bx)
            keep_scores.append(scores[kept, c])
            keep_labels.append(torch.full((kept.numel(),), c, dtype=torch.int64, device=bx.device))
        if keep_boxes:
            bx, sc, lb = torch.cat(keep_boxes), torch.cat(keep_scores), torch.cat(keep_labels)
            order = torch.argsort(sc, descending=True, stable=True)
            out.append(Detections(bx[order], sc[order], lb[order]))
        else:
            out.append(
                Detections(
                    boxes.new_zeros((0, 7)),
                    scores.new_zeros((0,)),
                    torch.zeros(0, dtype=torch.int64, device=boxes.device),
                )
            )
    return out
