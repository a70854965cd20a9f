"""The dense network as one exportable module: pseudo-image canvas → head output, every BatchNorm folded.

Voxelization, the pillar net, the scatter into the canvas and box decoding + NMS stay outside (as mmdeploy, Autoware
and Intel's OpenVINO PointPillars deploy it). Inside: the SECOND backbone (each 3x3 conv with its BatchNorm folded into
its weight and a bias), the FPN neck (each transposed conv folded likewise) and the head's three 1x1 convs as one conv
of their stacked weights (:meth:`detector.models.head.AnchorHead.fused`), so the graph is Conv / ConvTranspose / Relu /
Concat only. Input ``canvas`` (1, C, ny, nx) NCHW float32; output ``head`` (1, O, H, W), channel-planar like the eager
head's (rows cls, reg, dir).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from detector.models import PointPillars


def fold_conv_bn(conv: nn.Conv2d | nn.ConvTranspose2d, bn: nn.BatchNorm2d) -> nn.Conv2d | nn.ConvTranspose2d:
    """A plain ``nn.Conv2d`` / ``nn.ConvTranspose2d`` equal to ``bn(conv(x))`` in eval mode (running statistics)."""
    transpose = isinstance(conv, nn.ConvTranspose2d)
    # a plain torch layer first: the neck's ConvTranspose2dStandardGrad only changes the backward, which export drops
    plain = (nn.ConvTranspose2d if transpose else nn.Conv2d)(
        conv.in_channels, conv.out_channels, conv.kernel_size, stride=conv.stride, padding=conv.padding,
        bias=conv.bias is not None)
    plain.load_state_dict(conv.state_dict())
    return fuse_conv_bn_eval(plain.eval(), bn.eval(), transpose=transpose)


def fold_sequence(layers: nn.Sequential) -> nn.Sequential:
    """``[conv, BatchNorm2d, ReLU, ...]`` → ``[folded conv, ReLU, ...]`` (every conv followed by its BatchNorm)."""
    out: list[nn.Module] = []
    mods = list(layers)
    i = 0
    while i < len(mods):
        m = mods[i]
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)) and i + 1 < len(mods) and isinstance(mods[i + 1],
                                                                                              nn.BatchNorm2d):
            out.append(fold_conv_bn(m, mods[i + 1]))
            i += 2
        elif isinstance(m, nn.ReLU):
            out.append(nn.ReLU())  # not in place: exporters keep the graph pure
            i += 1
        else:
            raise ValueError(f"cannot fold layer {type(m).__name__} (expected conv, BatchNorm2d, ReLU)")
    return nn.Sequential(*out)


class DenseGraph(nn.Module):
    """canvas (1, C, ny, nx) → head output (1, O, H, W) of a dense :class:`PointPillars`, BatchNorm folded."""

    def __init__(self, model: PointPillars) -> None:
        super().__init__()
        if model.sparse_input or model.neck is None:
            raise ValueError("DenseGraph takes a dense model (backbone: dense)")
        self.canvas_shape: tuple[int, int] = model.output_shape  # (ny, nx) of the input canvas
        self.blocks = nn.ModuleList(fold_sequence(b) for b in model.backbone.blocks)
        self.deblocks = nn.ModuleList(fold_sequence(d) for d in model.neck.deblocks)
        weight, bias = model.anchor_head.fused()
        self.head = nn.Conv2d(weight.shape[1], weight.shape[0], 1)
        with torch.no_grad():
            self.head.weight.copy_(weight[:, :, None, None])
            self.head.bias.copy_(bias)
        self.eval()

    def forward(self, canvas: torch.Tensor) -> torch.Tensor:
        """canvas (1, C, ny, nx) → (1, O, ny/2, nx/2) planar head output."""
        x, ups = canvas, []
        for block, deblock in zip(self.blocks, self.deblocks):
            x = block(x)
            ups.append(deblock(x))
        return self.head(torch.cat(ups, dim=1))
