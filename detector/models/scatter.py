"""Dense scatter: pillar features → pseudo-image (the paper's "Feature Net" timer for the dense model).

Pillar ``(b, iy, ix)`` lands at flat index ``iy * nx + ix`` of sample ``b``'s zero canvas; cells without a pillar stay
exactly zero (that is what makes the sparse head exact downstream). The scatter writes in place into one zero canvas
with :func:`detector.sparse.tensor.scatter_to_dense`, the same code that densifies the sparse model's neck output.

**Layout.** :func:`canvas_channels_last` picks the memory format of every dense pseudo-image (this canvas, the sparse
ablations' dense tail): channels-last for inference and bf16 training, NCHW for fp32 training, whichever is faster
there (measured on a 2-core AVX2 CPU, 2 threads: fp32 inference of the 768 x 512 dense backbone + neck 1.1-1.4x faster
channels-last, the head 3-6x; an fp32 training step of the 288 x 144 CPU config 1.25x *slower* channels-last; bf16
training 1.25x faster channels-last on AVX512-BF16, docs/training.md). The convolutions keep the layout they are
given, so the backbone, neck and head run in it too, and the dense model hands the head the same channels-last map as
the sparse model (docs/benchmarks.md, "Shared components").
"""

from __future__ import annotations

import torch

from detector.sparse.indices import flat_keys
from detector.sparse.tensor import scatter_to_dense
from detector.sparse.workspace import Workspace


def canvas_channels_last(device_type: str) -> bool:
    """Whether dense pseudo-images are built channels-last in the current mode: True without autograd (inference)
    and under bfloat16 autocast on ``device_type``; False for fp32 training (where NCHW is faster)."""
    if not torch.is_grad_enabled():
        return True
    return torch.is_autocast_enabled(device_type) and torch.get_autocast_dtype(device_type) == torch.bfloat16


def scatter_to_canvas(
    features: torch.Tensor,
    coords: torch.Tensor,
    batch_size: int,
    output_shape: tuple[int, int],
    channels_last: bool = False,
    workspace: Workspace | None = None,
    owner: object | None = None,
) -> torch.Tensor:
    """features (P, C), coords (P, 3) int64 [b, iy, ix] → canvas (B, C, ny, nx), zero where no pillar.

    Coordinates must be unique and inside the canvas (the voxelizer guarantees both). One zero canvas, written in
    place; ``channels_last=True`` returns it with ``torch.channels_last`` strides (the (B, ny, nx, C) buffer viewed as
    (B, C, ny, nx), no copy), otherwise contiguous NCHW. The values are the same either way; autograd flows to
    ``features`` (the backward is a gather). ``workspace`` (inference): the canvas is ``owner``'s reused buffer, where
    only the previous call's pillars are reset (``detector.sparse.workspace``), valid until ``owner`` scatters again.
    """
    keys = flat_keys(coords, output_shape)
    if channels_last:
        return scatter_to_dense(features, keys, output_shape, batch_size, channels_first=False, workspace=workspace,
                                owner=owner).permute(0, 3, 1, 2)
    return scatter_to_dense(features, keys, output_shape, batch_size, workspace=workspace, owner=owner)

