"""Active-site normalisation and activation: inactive sites are never touched, so they stay exactly zero."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from detector.sparse.modules import SparseModule
from detector.sparse.phases import phase
from detector.sparse.tensor import SparseTensor
from detector.sparse.workspace import inference_workspace


class SparseBatchNorm(nn.BatchNorm1d, SparseModule):
    """``BatchNorm1d`` over the active rows ``(N, C)``, statistics pooled over the whole batch.

    Same parameters, buffers and ``state_dict`` keys as ``nn.BatchNorm2d(num_features, eps, momentum)``, so weights
    copy from a dense model. Defaults follow the reference (eps 1e-3, momentum 0.01).
    """

    def __init__(self, num_features: int, eps: float = 1e-3, momentum: float = 0.01, affine: bool = True) -> None:
        super().__init__(num_features, eps=eps, momentum=momentum, affine=affine)

    def forward(self, x: SparseTensor) -> SparseTensor:  # type: ignore[override]
        if x.features.shape[0] == 0:
            # no active site anywhere in the batch: nothing to normalise, and empty batch statistics would write NaN
            # into the running buffers
            return x
        ws = inference_workspace(x.workspace)
        with phase("bn_relu"):
            if ws is None or self.training or self.running_mean is None or self.running_var is None:
                out = super().forward(x.features)
            else:
                # inference into a reused buffer: batch_norm's own kernel (its out= form), so the values are the same
                f = x.features
                out = batch_norm_into(self, f, ws.take(self, "out", f.shape, f.dtype, f.device))
        return x.replace_feature(out)


def batch_norm_into(norm: nn.modules.batchnorm._BatchNorm, x: Tensor, out: Tensor) -> Tensor:
    """Eval-mode ``norm(x)`` written into ``out`` (which may be ``x`` itself: in place), the same values as
    ``norm(x)`` (aten's ``native_batch_norm.out``, i.e. the kernel ``F.batch_norm`` runs; a bfloat16 ``x`` with
    float32 statistics is fine, as in ``F.batch_norm``). Inference only (autograd off)."""
    stats = norm.running_mean if norm.running_mean is not None else x  # the dtype of the saved statistics
    torch.ops.aten.native_batch_norm.out(x, norm.weight, norm.bias, norm.running_mean, norm.running_var, False, 0.0,
                                         norm.eps, out=out, save_mean=stats.new_empty(0),
                                         save_invstd=stats.new_empty(0))
    return out


class SparseReLU(SparseModule):
    """ReLU on the active rows."""

    def forward(self, x: SparseTensor) -> SparseTensor:
        ws = inference_workspace(x.workspace)
        f = x.features
        with phase("bn_relu"):
            out = F.relu(f) if ws is None else torch.clamp_min(f, 0, out=ws.take(self, "out", f.shape, f.dtype,
                                                                                 f.device))
        return x.replace_feature(out)
