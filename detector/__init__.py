"""detector: dense PointPillars vs Sparse PointPillars on KITTI-format data (mpchair output or real KITTI).

``config`` (the experiment schema), ``device``, ``data/`` (KITTI dataset, augmentation, GT database, collate, a
config's view of the data), ``sparse/`` (pure-PyTorch sparse tensors and convolutions), ``ops/`` (exact rotated IoU
and NMS), ``eval/`` (the KITTI protocol), ``models/`` (voxelizer to head, one builder), ``checkpoint`` (the one model
loader), ``infer``, ``train/``, ``bench/``, ``stream/`` (streaming AP) and ``commands/``. Imports the shared floor of
``mpchair`` (``core``, ``kitti``, ``geometry``, ``recording``) and nothing else of it; the paper's experiment, which
drives this package, is the package ``reproduction`` above it (``docs/design.md``, ``tests/test_layout.py``).
"""

__version__ = "0.1.0"
