"""The weight gradients DDP expects: each with its weight's own (row-major) strides.

On a ``torch.channels_last`` map (the CPU canvas layout when training in bf16, and the sparse model's map, see
:func:`detector.models.scatter.canvas_channels_last`) the weight gradient of a 1x1 convolution or transposed
convolution comes back with the map's strides on its size-1 kernel dims: ``(96, 1, 96, 96)`` for a ``(2, 96, 1, 1)``
weight. Autograd accepts that (the strides of size-1 dims do not matter to its layout contract), but DDP compares
strides exactly with its bucket views and warned, once per rank, "Grad strides do not match bucket view strides".
:func:`standard_grad_strides` wraps a weight where it is used so that its gradient arrives with the weight's strides:
one small copy of a 1x1 kernel's gradient per step, no value changed.
"""

from __future__ import annotations

import torch
from torch import nn


class _StandardGradStrides(torch.autograd.Function):
    """Identity forward; backward hands on the gradient with the forward input's strides."""

    @staticmethod
    def forward(ctx, weight: torch.Tensor) -> torch.Tensor:
        ctx.strides = weight.stride()
        return weight.view_as(weight)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        return grad if grad.stride() == ctx.strides else grad.clone(memory_format=torch.contiguous_format)


def standard_grad_strides(weight: torch.Tensor) -> torch.Tensor:
    """``weight`` itself (same values, a view) whose gradient is handed on with ``weight``'s strides."""
    return _StandardGradStrides.apply(weight) if weight.requires_grad and torch.is_grad_enabled() else weight


def conv2d(module: nn.Conv2d, x: torch.Tensor) -> torch.Tensor:
    """``module(x)`` for an ``nn.Conv2d``, its weight gradient with the weight's strides."""
    return module._conv_forward(x, standard_grad_strides(module.weight), module.bias)


class ConvTranspose2dStandardGrad(nn.ConvTranspose2d):
    """``nn.ConvTranspose2d`` (same parameters, same numbers) whose weight gradient has the weight's strides."""

    def forward(self, input: torch.Tensor, output_size: list[int] | None = None) -> torch.Tensor:
        output_padding = self._output_padding(input, output_size, self.stride, self.padding, self.kernel_size, 2,
                                              self.dilation)
        return nn.functional.conv_transpose2d(input, standard_grad_strides(self.weight), self.bias, self.stride,
                                              self.padding, output_padding, self.groups, self.dilation)
