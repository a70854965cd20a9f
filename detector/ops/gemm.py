"""The inference GEMM of both models: ``x @ weight.t() (+ bias)`` through oneDNN on the CPU in float32.

Why not ``torch.mm``: PyTorch's float32 ``mm`` / ``addmm`` / ``F.linear`` on the CPU call MKL's sgemm, while its
convolutions run in oneDNN. On AMD CPUs MKL dispatches its AVX2 kernels even where the CPU has AVX-512, so a float32
GEMM there runs at about half the speed the same CPU gives a convolution. Measured on the 2-core AMD EPYC (AVX-512,
AVX512-BF16), torch 2.13, CPU time per call at 1 thread: the sparse model's block-3 SubM GEMM (300, 2304) x (2304,
256) 3.05 ms in MKL, 1.29 ms in oneDNN; block 1 (1200, 576) x (576, 64) 0.78 vs 0.33 ms; the neck's (300, 256) x
(256, 2048) 2.64 vs 1.13 ms; the dense neck's (98304, 64) x (64, 128) 32.3 vs 24.4 ms (``tools/bench_gemm.py``).
On Intel CPUs the two libraries are close. The dense backbone's convolutions are oneDNN already, so routing every
other inference GEMM of both models (the sparse convs, the exact head, the dense neck's levels) through oneDNN is
what makes the dense / sparse comparison like with like: one GEMM library on both sides.

The oneDNN call is ``torch.ops.mkldnn._linear_pointwise``, the op PyTorch's own inductor emits for CPU linears (a
private op, hence this one wrapper; the version is pinned). It takes the plain ``(O, K)`` weight (transposed views
too) and allocates its output. It has no autograd formula, so :class:`OneDNNLinear` gives it one whose backward is two
more oneDNN GEMMs (``g @ W`` and ``g.t() @ x``, on views): training's GEMMs run in the library of the dense model's
training convolutions as well. oneDNN has no float64 GEMM, so float64 (the exactness tests) keeps ``torch.mm``, and so
do bf16 (whose ``mm`` is oneDNN already) and autocast regions. Results differ from MKL's by float rounding only
(another summation order; tested to 1e-5 relative).

``BACKEND`` picks the library: ``"auto"`` (oneDNN where it applies, the default), ``"mkl"`` (always ``torch.mm``;
``tools/bench_gemm.py`` flips it between frames to time both in one process). The environment variable
``DETECTOR_GEMM`` sets it at import.
"""

from __future__ import annotations

import os
from typing import Any

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

#: ``"auto"`` (oneDNN for float32 CPU inference) or ``"mkl"`` (``torch.mm`` always); see the module docstring.
BACKEND: str = os.environ.get("DETECTOR_GEMM", "auto")
if BACKEND not in ("auto", "mkl"):
    raise ValueError(f"DETECTOR_GEMM must be 'auto' or 'mkl', got {BACKEND!r}")

_HAVE_ONEDNN = torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_linear_pointwise")


def library() -> str:
    """The library of eager float32 CPU GEMMs under the current ``BACKEND``: ``"onednn"`` or ``"mkl"`` (recorded with
    every timing, :func:`detector.device.machine_info`)."""
    return "onednn" if BACKEND == "auto" and _HAVE_ONEDNN else "mkl"


def uses_onednn(x: Tensor, weight: Tensor) -> bool:
    """Whether :func:`linear` of these operands runs in oneDNN: ``BACKEND`` auto, float32 CPU tensors, outside
    autocast."""
    return (
        BACKEND == "auto"
        and _HAVE_ONEDNN
        and x.device.type == "cpu"
        and x.dtype == weight.dtype == torch.float32
        and not torch.is_autocast_enabled("cpu")
    )


def _onednn(x: Tensor, weight: Tensor, bias: Tensor | None = None, attr: str = "none") -> Tensor:
    return torch.ops.mkldnn._linear_pointwise(x, weight, bias, attr, [], "")


class OneDNNLinear(torch.autograd.Function):
    """``x @ weight.t() (+ bias)`` in oneDNN with a backward in oneDNN: ``grad_x = g @ weight``, ``grad_weight = g.t()
    @ x`` (both GEMMs on transposed views, no copies), ``grad_bias = g.sum(0)``."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
        ctx.save_for_backward(x, weight)
        ctx.has_bias = bias is not None
        return _onednn(x, weight, bias)

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, g: Tensor) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
        x, weight = ctx.saved_tensors
        g = g.contiguous()
        gx = _onednn(g, weight.t()) if ctx.needs_input_grad[0] else None
        gw = _onednn(g.t(), x.t()) if ctx.needs_input_grad[1] else None
        gb = g.sum(0) if ctx.has_bias and ctx.needs_input_grad[2] else None
        return gx, gw, gb


def linear(x: Tensor, weight: Tensor, bias: Tensor | None = None, *, relu: bool = False) -> Tensor:
    """``(M, K)`` rows times an ``(O, K)`` weight (any strides) → ``(M, O)``: ``x @ weight.t() (+ bias)``, then ReLU
    if ``relu``. A new tensor, in oneDNN where :func:`uses_onednn` says so (with :class:`OneDNNLinear`'s backward
    when autograd records it), else ``torch.mm`` / ``addmm`` (MKL)."""
    if uses_onednn(x, weight) and (bias is None or bias.dtype == torch.float32):
        grad = torch.is_grad_enabled() and (x.requires_grad or weight.requires_grad
                                            or (bias is not None and bias.requires_grad))
        if not grad:
            return _onednn(x, weight, bias, "relu" if relu else "none")
        y = OneDNNLinear.apply(x, weight, bias)
        return torch.relu(y) if relu else y
    y = x @ weight.t() if bias is None else torch.addmm(bias, x, weight.t())
    return y.relu_() if relu else y
