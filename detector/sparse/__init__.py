"""Pure-PyTorch sparse 2-D convolution for Sparse PointPillars: a ``SparseTensor`` (features on active BEV sites with
``[batch, iy, ix]`` grid coordinates), submanifold, down-sampling and transposed convolutions that equal their dense
``torch.nn`` twins on the active sites (same weight layout, so weights copy across), active-site BatchNorm/ReLU and a
``SparseSequential``. Neighbour tables are built by vectorised lookups (``indices``) and cached per site set under an
``indice_key``; there is no global state, and everything runs on the device of its inputs. See ``docs/sparse.md``.
"""

from detector.sparse.conv import (
    SparseConv2d,
    SparseConvTranspose2d,
    SubMConv2d,
    conv_matrix,
    gather_gemm,
    gemm_gather,
    padded_rows,
    subm_conv2d,
    transposed_matrix,
)
from detector.sparse.indices import (
    DownTable,
    SiteLookup,
    SubMTable,
    UpTable,
    down_table,
    subm_table,
    up_table,
    wide_down_table,
)
from detector.sparse.modules import SparseModule, SparseSequential
from detector.sparse.norm import SparseBatchNorm, SparseReLU
from detector.sparse.tensor import SparseTensor, scatter_to_dense
from detector.sparse.workspace import Workspace

__all__ = [
    "DownTable",
    "SiteLookup",
    "SparseBatchNorm",
    "SparseConv2d",
    "SparseConvTranspose2d",
    "SparseModule",
    "SparseReLU",
    "SparseSequential",
    "SparseTensor",
    "SubMConv2d",
    "SubMTable",
    "UpTable",
    "Workspace",
    "conv_matrix",
    "down_table",
    "gather_gemm",
    "gemm_gather",
    "padded_rows",
    "scatter_to_dense",
    "subm_conv2d",
    "subm_table",
    "transposed_matrix",
    "up_table",
    "wide_down_table",
]
