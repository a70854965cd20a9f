"""Detection losses (Open3D-ML ``Anchor3DHead`` settings), separate from ``forward``.

| term | definition | default weight |
|---|---|---|
| cls | sigmoid focal loss (alpha 0.25, gamma 2) over positive and negative anchors, one-hot, no background | 1.0 |
| reg | smooth L1 (beta 0.11) over the 7 residuals of positives; yaw by the sine difference sin(p - t) | 2.0 |
| dir | 2-bin cross-entropy over positives | 0.2 |

All three are sums divided by ``max(1, #positives over the whole batch)`` (Open3D-ML normalises by the batch total;
the max(1, .) makes a batch without positives well defined, where SPP summed unnormalised losses).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F

from detector.models.assign import Targets
from detector.models.head import HeadOutput


class Losses(NamedTuple):
    """A batch's loss terms, each already weighted, and ``total``, their sum: scalar tensors from
    :func:`compute_loss`; floats once training has detached and summed them over ranks for its log."""

    cls: torch.Tensor | float
    reg: torch.Tensor | float
    dir: torch.Tensor | float
    total: torch.Tensor | float


def sigmoid_focal_loss(logits: torch.Tensor, targets: torch.Tensor, alpha: float, gamma: float) -> torch.Tensor:
    """Elementwise focal loss: logits (...), targets (...) in {0, 1} → (...) ``-alpha_t (1 - p_t)^gamma log p_t``."""
    p = torch.sigmoid(logits)
    pt = (1 - p) * targets + p * (1 - targets)  # 1 - p_t
    weight = (alpha * targets + (1 - alpha) * (1 - targets)) * pt.pow(gamma)
    return F.binary_cross_entropy_with_logits(logits, targets, reduction="none") * weight


def smooth_l1(diff: torch.Tensor, beta: float) -> torch.Tensor:
    """Elementwise smooth L1 of a difference: ``0.5 d^2 / beta`` if ``|d| < beta`` else ``|d| - 0.5 beta``."""
    d = diff.abs()
    return torch.where(d < beta, 0.5 * d * d / beta, d - 0.5 * beta)


def add_sin_difference(pred: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Replace the yaw column: pred → sin(p)cos(t), target → cos(p)sin(t), so their difference is sin(p - t)."""
    p, t = pred[..., 6:7], target[..., 6:7]
    pred = torch.cat([pred[..., :6], torch.sin(p) * torch.cos(t)], dim=-1)
    target = torch.cat([target[..., :6], torch.cos(p) * torch.sin(t)], dim=-1)
    return pred, target


def compute_loss(
    preds: HeadOutput,
    targets: Targets,
    *,
    num_classes: int,
    focal_alpha: float = 0.25,
    focal_gamma: float = 2.0,
    cls_weight: float = 1.0,
    smooth_l1_beta: float = 0.11,
    reg_weight: float = 2.0,
    dir_weight: float = 0.2,
) -> Losses:
    """Losses of a batch. preds: head output, cls (B, H, W, A*K), reg (B, H, W, A*7), dir (B, H, W, A*2), flattened in
    anchor order (y, x, anchor) to match ``targets`` (B, H*W*A). Returns :class:`Losses` of scalar tensors
    (``cls``/``reg``/``dir`` already weighted; ``total`` is their sum)."""
    b = preds.cls.shape[0]
    cls = preds.cls.reshape(b, -1, num_classes)
    reg = preds.reg.reshape(b, -1, 7)
    dirs = preds.dir.reshape(b, -1, 2)
    if cls.shape[1] != targets.pos.shape[1]:
        raise ValueError(f"compute_loss: {cls.shape[1]} predicted anchors but {targets.pos.shape[1]} targets")
    num_pos = targets.pos.sum().clamp(min=1).to(cls.dtype)
    pos, care = targets.pos, targets.pos | targets.neg
    onehot = F.one_hot(targets.labels, num_classes).to(cls.dtype) * pos[..., None].to(cls.dtype)
    loss_cls = sigmoid_focal_loss(cls[care], onehot[care], focal_alpha, focal_gamma).sum() / num_pos
    p, t = add_sin_difference(reg[pos], targets.reg[pos].to(reg.dtype))
    loss_reg = smooth_l1(p - t, smooth_l1_beta).sum() / num_pos
    loss_dir = F.cross_entropy(dirs[pos], targets.dir[pos], reduction="sum") / num_pos
    weighted_cls, weighted_reg, weighted_dir = cls_weight * loss_cls, reg_weight * loss_reg, dir_weight * loss_dir
    return Losses(cls=weighted_cls, reg=weighted_reg, dir=weighted_dir,
                  total=weighted_cls + weighted_reg + weighted_dir)
