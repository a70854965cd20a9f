"""Dense SECOND backbone (the paper's Fig. 5a): three blocks of 3x3 convs, each starting with a stride-2 conv.

Block i: Conv2d(3x3, stride s_i, pad 1) → BN → ReLU, then ``L_i`` x (Conv2d 3x3 pad 1 → BN → ReLU). Channels
64/128/256, L = 3/5/5, strides 2/2/2. No conv biases (BN follows); BN eps 1e-3, momentum 0.01.

Init: Kaiming normal (fan_out, ReLU gain), the init mmdet3d's ``SECOND`` declares (``init_cfg`` Kaiming on Conv2d),
which our checkpoints were trained with. The reference does *not* do this: Open3D-ML's (and SPP's) ``SECOND`` has no
init of its own, so its convs keep PyTorch's default (``kaiming_uniform_(a=sqrt(5))``: 1/sqrt(6) of this std where
C_in = C_out), and its ``SECONDFPN.init_weights`` applies Kaiming normal to ``nn.Conv2d`` layers only, of which the
neck has none (its levels are ``ConvTranspose2d``).

:func:`dense_block` is public so the sparse ablations (Sparse1+Dense23, Sparse12+Dense3) can build their dense tail
from the same parts.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from detector.models.pillar_net import BN_EPS, BN_MOMENTUM
from detector.sparse.norm import batch_norm_into


def conv_bn_relu(in_channels: int, out_channels: int, *, kernel_size: int = 3, stride: int = 1) -> list[nn.Module]:
    """[Conv2d(k, stride, pad k//2, no bias), BatchNorm2d(eps 1e-3, mom 0.01), ReLU] as a list of layers."""
    conv = nn.Conv2d(in_channels, out_channels, kernel_size, stride=stride, padding=kernel_size // 2, bias=False)
    nn.init.kaiming_normal_(conv.weight, mode="fan_out", nonlinearity="relu")
    return [conv, nn.BatchNorm2d(out_channels, eps=BN_EPS, momentum=BN_MOMENTUM), nn.ReLU(inplace=True)]


def dense_block(in_channels: int, out_channels: int, num_layers: int, stride: int) -> nn.Sequential:
    """One SECOND block: a 3x3 stride-``stride`` conv then ``num_layers`` 3x3 convs, each with BN + ReLU.

    (B, in_channels, H, W) → (B, out_channels, H / stride, W / stride) (H, W divisible by ``stride``).
    """
    layers = conv_bn_relu(in_channels, out_channels, stride=stride)
    for _ in range(num_layers):
        layers += conv_bn_relu(out_channels, out_channels)
    return nn.Sequential(*layers)


class SecondBackbone(nn.Module):
    """(B, in_channels, ny, nx) pseudo-image → list of ``len(layer_channels)`` maps, level i at stride
    prod(layer_strides[:i+1]) with ``layer_channels[i]`` channels."""

    def __init__(
        self,
        *,
        in_channels: int,
        layer_channels: Sequence[int],
        layer_nums: Sequence[int],
        layer_strides: Sequence[int],
    ) -> None:
        super().__init__()
        if not (len(layer_channels) == len(layer_nums) == len(layer_strides)):
            raise ValueError("SecondBackbone: layer_channels, layer_nums and layer_strides must have equal lengths")
        ins = [in_channels, *layer_channels[:-1]]
        self.blocks = nn.ModuleList(
            dense_block(i, o, n, s) for i, o, n, s in zip(ins, layer_channels, layer_nums, layer_strides)
        )

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """x (B, C, ny, nx) → [(B, C_1, ny/2, nx/2), (B, C_2, ny/4, nx/4), (B, C_3, ny/8, nx/8)] for strides 2/2/2.

        Inference (eval, autograd off) runs every BatchNorm in place on its conv's fresh output (batch_norm's own
        kernel, so the same values): one activation buffer per layer instead of two (a 25 MB map at 768 x 512)."""
        outs = []
        in_place = not self.training and not torch.is_grad_enabled()
        for block in self.blocks:
            if in_place:
                for layer in block:
                    x = batch_norm_into(layer, x, x) if isinstance(layer, nn.BatchNorm2d) else layer(x)
            else:
                x = block(x)
            outs.append(x)
        return outs
