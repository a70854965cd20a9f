"""mpchair: build the Matterport-Chair 3D detection dataset (KITTI format) from Matterport3D house meshes.

The shared floor, used by both ``mpchair`` and ``detector``: ``core/`` (errors, atomic writes, the folder lock, YAML
configs, text files, numba cache, malloc tuning, CLI helpers), ``paper`` (the Sparse PointPillars paper's published
figures), ``kitti/`` (KITTI file formats), ``geometry/`` (frames, boxes, pillars and the pseudoimage grid) and
``recording/`` (Rerun and ROS 2 / MCAP recordings). Then the dataset stack, one folder per stage: ``matterport/``
(read the release and habitat layouts), ``synth/`` (procedural houses in those formats), ``scan/`` (sensors,
viewpoints, raycasting), ``labels/`` (boxes and filters), ``dataset/`` (frames, typed manifest records,
orchestration), ``stream/`` (robot episodes), ``analysis/`` (stats and pictures) and ``commands/`` (the CLI). Which
folder may import which: ``docs/design.md``.
"""

__version__ = "0.1.0"

# Before anything imports numpy: one OpenBLAS kernel on AVX2 and AVX-512 CPUs (same seed, same bytes; core/blas.py).
from mpchair.core.blas import pin_openblas_kernel as _pin_openblas_kernel  # noqa: E402

_pin_openblas_kernel()
