"""The GEMM of both models: ``x @ weight.t() (+ bias)`` through oneDNN on the CPU in float32 (inference and training).

Why not ``torch.mm``: PyTorch's float32 ``mm`` / ``addmm`` / ``F.linear`` on the CPU call MKL's sgemm, while its
convolutions run in oneDNN. On AMD CPUs MKL dispatches its AVX2 kernels even where the CPU has AVX-512, so a float32
GEMM there runs at about half the speed the same CPU gives a convolution. Measured on the 2-core AMD EPYC (AVX-512,
AVX512-BF16), torch 2.13, 2 threads, minimum of 20 calls (``tools/bench_gemm.py``, docs/sparse.md "GEMM library"):
the sparse model's block-3 SubM GEMM (150, 2304) x (2304, 256) 0.78 ms in MKL, 0.35 ms in oneDNN; block 1 (1200,
576) x (576, 64) 0.39 vs 0.20 ms; a 4 MiB chunk of the dense neck's level 3, (512, 256) x (256, 2048), 2.45 vs 1.12
ms. The dense backbone's convolutions are oneDNN already (in training too), so routing every other GEMM of both
models (the sparse convs, the exact head, the dense neck's levels and head; the sparse model's training products)
through oneDNN is what makes the dense / sparse comparison like with like: one GEMM library on both sides.

The oneDNN call is ``torch.ops.mkldnn._linear_pointwise``, the op PyTorch's own inductor emits for CPU linears (a
private op, hence this one wrapper; the version is pinned). It takes the plain ``(O, K)`` weight (transposed views
too) and allocates its output. oneDNN builds (JIT-compiles) a kernel per operand shape and caches it: a shape it has
not seen costs far more than a cached one (``tools/bench_gemm.py``'s "new shape" row), and the sparse
convs' row counts change every frame. So callers with a varying row count hand it a buffer of :func:`bucket_rows`
rows (the first ``m`` being theirs, the rest ignored) and keep the first ``m`` output rows: about 50 shapes per
weight over 64..8,192 rows, at most 12.5 % (about 6 % on average) extra rows. Training's products take it as well
(:func:`train_linear`, and ``SubMGemm`` in ``detector.sparse.autograd``): the rows zero-padded to a bucket, so the
weight gradient's sum over rows is unchanged, and the backward's two products at the same row count. Only in
float32: oneDNN has no float64 GEMM (the exactness tests run float64) and bf16's ``mm`` is oneDNN already. Results
differ from MKL's by float rounding only (another summation order; tested to 1e-5 relative).

The library is an explicit choice, :func:`gemm_backend`: ``with gemm_backend("mkl"):`` runs the block's products in
``torch.mm`` (MKL), ``"auto"`` (the default outside any block) in oneDNN where it applies. The choice is a context
variable, so it is scoped to the block (and its thread); ``tools/bench_gemm.py`` switches it between frames to time
both in one process. The ``detector`` CLI reads the environment variable ``DETECTOR_GEMM`` once
(:func:`parse_backend`) and runs the command inside the block; nothing here reads the environment. It lives in
``detector/ops`` because the dense neck and head call it as much as the sparse convs do.
"""

from __future__ import annotations

from collections.abc import Hashable, Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any, Literal, Protocol, get_args

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from mpchair.core.errors import InputError

#: ``"auto"`` (oneDNN for float32 CPU GEMMs) or ``"mkl"`` (``torch.mm`` always); see the module docstring.
Backend = Literal["auto", "mkl"]
BACKENDS: tuple[str, ...] = get_args(Backend)
#: The choice of the enclosing :func:`gemm_backend` block ("auto" outside any).
_BACKEND: ContextVar[str] = ContextVar("detector_gemm_backend", default="auto")


def _onednn_linear_available() -> bool:
    """Whether this torch build has the private oneDNN linear op :func:`_onednn_linear` calls (else every product
    falls back to ``torch.mm``)."""
    return torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_linear_pointwise")


HAVE_ONEDNN: bool = _onednn_linear_available()


def _onednn_linear(x: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
    """``x @ weight.t() (+ bias)`` in oneDNN: the one call of a private PyTorch op in the project.

    ``torch.ops.mkldnn._linear_pointwise`` is the op PyTorch's inductor emits for CPU linears; no public API reaches
    oneDNN's GEMM for float32 (``torch.mm`` goes to MKL; see the module docstring for why that matters). Being
    private it may change or go with a torch release (the version is pinned): :data:`HAVE_ONEDNN` checks it exists,
    and without it :func:`uses_onednn` is False everywhere, so every caller takes ``torch.mm`` instead."""
    return torch.ops.mkldnn._linear_pointwise(x, weight, bias, "none", [], "")


def parse_backend(value: str, source: str = "DETECTOR_GEMM") -> Backend:
    """``value`` as a :data:`Backend`; anything else is an :class:`InputError` naming ``source`` (one line)."""
    if value not in BACKENDS:
        raise InputError(f"{source} must be one of {', '.join(BACKENDS)}, got {value!r}")
    return value  # type: ignore[return-value]


@contextmanager
def gemm_backend(backend: str) -> Iterator[None]:
    """Run the block's float32 CPU GEMMs under ``backend`` (``"auto"``: oneDNN where it applies; ``"mkl"``:
    ``torch.mm`` always); the previous choice returns when the block ends."""
    token = _BACKEND.set(parse_backend(backend, "the GEMM backend"))
    try:
        yield
    finally:
        _BACKEND.reset(token)


def current_backend() -> Backend:
    """The backend of the enclosing :func:`gemm_backend` block (``"auto"`` outside any)."""
    return _BACKEND.get()  # type: ignore[return-value]


def library(backend: str | None = None) -> str:
    """The library of eager float32 CPU GEMMs under ``backend`` (default: :func:`current_backend`): ``"onednn"`` or
    ``"mkl"`` (``detector bench`` records it, :func:`detector.bench.run.machine_record`)."""
    return "onednn" if (current_backend() if backend is None else backend) == "auto" and HAVE_ONEDNN else "mkl"


class BufferPool(Protocol):
    """What :func:`row_buffer` needs of a workspace (``detector.sparse.Workspace``): a reusable buffer per key."""

    def take(self, owner: Hashable, name: str, shape: Sequence[int], dtype: torch.dtype,
             device: torch.device | str) -> Tensor: ...


def trains_in_onednn(x: Tensor, weight: Tensor) -> bool:
    """Whether a product of these operands runs in oneDNN when autograd may record it (:func:`train_linear`,
    ``SubMGemm``): the backend ``"auto"``, float32 CPU tensors, outside autocast (bf16 autocast's ``mm`` is oneDNN
    already)."""
    return (
        library() == "onednn"
        and x.device.type == "cpu"
        and x.dtype == weight.dtype == torch.float32
        and not torch.is_autocast_enabled("cpu")
    )


def uses_onednn(x: Tensor, weight: Tensor) -> bool:
    """Whether :func:`linear` of these operands runs in oneDNN: :func:`trains_in_onednn`'s conditions, and autograd
    not recording them (recorded products take :func:`train_linear`)."""
    return trains_in_onednn(x, weight) and not (torch.is_grad_enabled() and (x.requires_grad or weight.requires_grad))


def bucket_rows(m: int) -> int:
    """The row count to run an ``m``-row GEMM at in oneDNN: ``m`` rounded up to a multiple of ``2**(b - 4)`` (``b``
    the bit length of ``m - 1``), at least 64: 8 to 16 sizes per octave, so a stream of frames reuses a few kernels."""
    if m <= 64:
        return 64
    step = 1 << ((m - 1).bit_length() - 4)
    return -(-m // step) * step


def linear(x: Tensor, weight: Tensor, bias: Tensor | None = None) -> Tensor:
    """``(M, K)`` rows times an ``(O, K)`` weight (any strides) → ``(M, O)``: ``x @ weight.t() (+ bias)``. A new
    tensor, in oneDNN where :func:`uses_onednn` says so, else ``torch.mm`` / ``addmm`` (MKL). Callers whose ``M``
    varies from call to call pass :func:`bucket_rows` rows (see the module docstring)."""
    if uses_onednn(x, weight) and (bias is None or bias.dtype == torch.float32):
        return _onednn_linear(x, weight, bias)
    return x @ weight.t() if bias is None else torch.addmm(bias, x, weight.t())


def row_buffer(m: int, cols: int, like: Tensor, workspace: BufferPool | None = None, owner: object | None = None,
               name: str = "rows") -> Tensor:
    """A ``(bucket_rows(m), cols)`` buffer of ``like``'s dtype and device (contents unspecified) for an ``m``-row
    oneDNN GEMM: ``owner``'s buffer ``name`` of ``workspace`` (reused from frame to frame), or a new tensor."""
    shape = (bucket_rows(m), cols)
    if workspace is None:
        return like.new_empty(shape)
    return workspace.take(owner, name, shape, like.dtype, like.device)


def linear_rows(x: Tensor, weight: Tensor, bias: Tensor | None = None, workspace: BufferPool | None = None,
                owner: object | None = None) -> Tensor:
    """:func:`linear` of rows whose count varies from call to call, in oneDNN: ``x`` copied into a :func:`row_buffer`
    (``owner``'s ``"rows"`` in ``workspace``, if given), the first ``len(x)`` output rows returned. Callers check
    :func:`uses_onednn` first (elsewhere ``linear`` itself is the right call)."""
    m = x.shape[0]
    rows = row_buffer(m, x.shape[1], x, workspace, owner)
    rows[:m].copy_(x)
    return linear(rows, weight, bias)[:m]


def _zero_padded(x: Tensor, rows: int) -> Tensor:
    """``x`` ``(M, K)`` as the first rows of a new ``(rows, K)`` matrix whose other rows are zero."""
    out = x.new_empty((rows, x.shape[1]))
    out[: x.shape[0]].copy_(x)
    out[x.shape[0]:].zero_()
    return out


class _BucketedLinear(torch.autograd.Function):
    """``x @ weight.t() (+ bias)`` for training in oneDNN: the rows zero-padded to :func:`bucket_rows` (one kernel per
    bucket, like inference), the forward and both gradient products (``g @ W``, ``g.t() @ x``) run at that row
    count. The padding rows are zero in ``x`` and in the output gradient, so the weight gradient's sum is unchanged."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
        m = x.shape[0]
        rows = _zero_padded(x, bucket_rows(m))
        ctx.save_for_backward(rows, weight)
        ctx.m = m
        return linear(rows, weight, bias)[:m]

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
        rows, weight = ctx.saved_tensors
        m = ctx.m
        g = _zero_padded(grad, rows.shape[0])
        grad_x = linear(g, weight.t())[:m] if ctx.needs_input_grad[0] else None  # (M, O) x (O, K)
        grad_w = linear(g.t(), rows.t()) if ctx.needs_input_grad[1] else None  # (O, M) x (M, K)
        grad_b = grad.sum(0) if ctx.needs_input_grad[2] else None
        return grad_x, grad_w, grad_b


def train_linear(x: Tensor, weight: Tensor, bias: Tensor | None = None) -> Tensor:
    """``x @ weight.t() (+ bias)`` with autograd: in oneDNN at a bucketed row count where :func:`trains_in_onednn`
    says so (forward and backward; docs/sparse.md "GEMM library"), else ``torch.nn.functional.linear`` (MKL)."""
    if trains_in_onednn(x, weight) and (bias is None or bias.dtype == torch.float32):
        return _BucketedLinear.apply(x, weight, bias)
    return torch.nn.functional.linear(x, weight, bias)
