"""Residual box coding between anchors and boxes (Open3D-ML ``BBoxCoder`` / OpenPCDet ``ResidualCoder``).

Boxes and anchors are (N, 7) ``[x, y, z_centre, l, w, h, yaw]`` (sensor frame, metres, yaw CCW rad). With the anchor
diagonal ``d = sqrt(l_a^2 + w_a^2)``: ``dx = (x_g - x_a)/d``, ``dy = (y_g - y_a)/d``, ``dz = (z_g - z_a)/h_a``,
``dl = log(l_g/l_a)``, ``dw = log(w_g/w_a)``, ``dh = log(h_g/h_a)``, ``dr = yaw_g - yaw_a``; residuals keep the box
column order. :func:`limit_period` is the torch twin of :func:`mpchair.geometry.wrap_angle` (same formula; that one
is float64 numpy without autograd).
"""

from __future__ import annotations

import math

import torch


def limit_period(angle: torch.Tensor, offset: float = 0.5, period: float = 2 * math.pi) -> torch.Tensor:
    """Wrap angles (rad) into ``[-offset, 1 - offset) * period``: ``a - floor(a / period + offset) * period``."""
    return angle - torch.floor(angle / period + offset) * period


def encode_boxes(boxes: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
    """boxes (..., 7), anchors (..., 7) → residuals (..., 7) ``[dx, dy, dz, dl, dw, dh, dr]`` (unitless / rad)."""
    xa, ya, za, la, wa, ha, ra = anchors.unbind(-1)
    xg, yg, zg, lg, wg, hg, rg = boxes.unbind(-1)
    d = torch.sqrt(la * la + wa * wa)
    return torch.stack(
        [
            (xg - xa) / d,
            (yg - ya) / d,
            (zg - za) / ha,
            torch.log(lg / la),
            torch.log(wg / wa),
            torch.log(hg / ha),
            rg - ra,
        ],
        dim=-1,
    )


def decode_boxes(deltas: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`encode_boxes`: residuals (..., 7), anchors (..., 7) → boxes (..., 7) (sensor frame)."""
    xa, ya, za, la, wa, ha, ra = anchors.unbind(-1)
    dx, dy, dz, dl, dw, dh, dr = deltas.unbind(-1)
    d = torch.sqrt(la * la + wa * wa)
    return torch.stack(
        [dx * d + xa, dy * d + ya, dz * ha + za, torch.exp(dl) * la, torch.exp(dw) * wa, torch.exp(dh) * ha, dr + ra],
        dim=-1,
    )
