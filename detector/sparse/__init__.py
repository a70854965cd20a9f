"""Pure-PyTorch sparse 2-D convolution for Sparse PointPillars: a ``SparseTensor`` (features on active BEV sites with
``[batch, iy, ix]`` grid coordinates), submanifold, down-sampling and transposed convolutions that equal their dense
``torch.nn`` twins on the active sites (same weight layout, so weights copy across), active-site BatchNorm/ReLU and a
``SparseSequential``. Neighbour tables are built by vectorised lookups (``indices``) and cached per site set under an
``indice_key``; there is no global state, and everything runs on the device of its inputs. See ``docs/sparse.md``.
"""

from detector.sparse.conv import SparseConv2d, SparseConvTranspose2d, SubMConv2d, subm_conv2d
from detector.sparse.indices import SiteLookup, SubMTable, down_table, subm_table, up_table
from detector.sparse.modules import SparseModule, SparseSequential
from detector.sparse.norm import SparseBatchNorm, SparseReLU
from detector.sparse.tensor import SparseTensor, scatter_to_dense

__all__ = [
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
    "down_table",
    "scatter_to_dense",
    "subm_conv2d",
    "subm_table",
    "up_table",
]
