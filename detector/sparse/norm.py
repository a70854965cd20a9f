"""Active-site normalisation and activation: inactive sites are never touched, so they stay exactly zero."""

from __future__ import annotations

import torch.nn.functional as F
from torch import nn

from detector.sparse.modules import SparseModule
from detector.sparse.tensor import SparseTensor


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
        return x.replace_feature(super().forward(x.features))


class SparseReLU(SparseModule):
    """ReLU on the active rows."""

    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.replace_feature(F.relu(x.features))
