"""detector: dense PointPillars vs Sparse PointPillars on KITTI-format data (mpchair output or real KITTI).

Stages, one folder each: ``data/`` (KITTI dataset, augmentation, GT database, collate), ``models/`` (voxelizer,
pillar net, backbones, neck, anchors, coder, assignment, losses, head, builder), ``sparse/`` (pure-PyTorch sparse
tensors and convolutions), ``ops/`` (exact rotated IoU and NMS), ``eval/`` (the KITTI protocol). Imports the shared
floor of ``mpchair`` (``geometry``, ``kitti``, ``errors``, ``atomic``, ``config``) and nothing else of it.
"""

__version__ = "0.1.0"
