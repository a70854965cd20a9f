"""Containers for sparse networks: a marker base class and a sequential that feeds plain ``nn`` layers features only."""

from __future__ import annotations

from torch import nn

from detector.sparse.tensor import SparseTensor


class SparseModule(nn.Module):
    """Base class of layers that take and return a ``SparseTensor`` (everything else gets ``x.features``)."""


class SparseSequential(nn.Sequential):
    """``nn.Sequential`` over ``SparseTensor``s (spconv's ``SparseSequential``).

    ``SparseModule`` children receive the whole tensor. Any other child (``nn.Linear``, ``nn.Dropout``, an activation)
    is applied to the ``(N, C)`` feature matrix and the result is put back on the same sites with
    ``replace_feature``, so it must act row-wise and keep the number of rows.
    """

    def forward(self, x: SparseTensor) -> SparseTensor:  # type: ignore[override]
        for module in self:
            x = module(x) if isinstance(module, SparseModule) else x.replace_feature(module(x.features))
        return x
