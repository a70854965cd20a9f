"""The reference's head layout at inference, for timing beside ours: three separate 1x1 convs on an NCHW map.

The reference (Open3D-ML's PointPillars, and SPP after its todense) runs the head's class, box and direction convs one
after the other on the NCHW 384-channel neck map, so the map is read three times and each conv takes PyTorch's NCHW
1x1 path. Ours (:class:`detector.models.head.AnchorHead` at inference) runs them as one fused GEMM over a
channels-last map. At 768 x 512 on a CPU the reference's layout takes several times as long as ours
(``tools/bench_reference_head.py`` measures both), so the head decides much of the dense / sparse total-time ratio.
:func:`reference_head` computes the same maps as the fused head (same parameters) in the reference's layout.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from detector.models.head import AnchorHead, HeadOutput


def reference_head(head: AnchorHead, x: torch.Tensor) -> HeadOutput:
    """``head``'s three 1x1 convs run separately on ``x`` (B, C, H, W) as the reference runs them: ``x`` should be NCHW
    (contiguous) for the reference's layout; the outputs are (B, H, W, C) views, as :class:`HeadOutput` holds them."""
    maps = (F.conv2d(x, m.weight, m.bias) for m in (head.conv_cls, head.conv_reg, head.conv_dir))
    return HeadOutput(*(y.permute(0, 2, 3, 1) for y in maps))


def nchw(x: torch.Tensor) -> torch.Tensor:
    """``x`` as an NCHW-contiguous tensor (a copy when it is channels-last): the map the reference's neck hands over."""
    return x.contiguous(memory_format=torch.contiguous_format)
