"""Head maps → detections (the paper's "BBox Extract" timer), Open3D-ML ``Anchor3DHead.get_bboxes`` semantics.

Per sample: sigmoid of the class logits; keep the top ``nms_pre`` anchors by their max class score over the whole map;
decode; per class, keep scores > ``score_thr`` and run greedy rotated BEV NMS (``detector.ops.rotated_nms``, IoU
``nms_iou``); then the direction fix ``yaw = wrap(yaw - dir_offset, dir_limit_offset, pi) + dir_offset + pi * bin``.
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

    Ties in the top-k (many anchors share the bias score on a sparse map) are resolved by ``torch.topk`` on the full
    score vector, so the dense head and the exact sparse head select the same anchors. Runs without autograd.
    """
    b = cls.shape[0]
    scores_all = torch.sigmoid(cls).reshape(b, -1, num_classes)
    if scores_all.shape[1] != anchors.shape[0]:
        raise ValueError(f"postprocess: {scores_all.shape[1]} predicted anchors but {anchors.shape[0]} anchors")
    out = []
    for i in range(b):
        scores = scores_all[i]
        k = min(nms_pre, scores.shape[0])
        top = torch.topk(scores.max(dim=1).values, k).indices
        scores, boxes = scores[top], decode_boxes(anchor_rows(reg[i], top, 7), anchors[top])
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
