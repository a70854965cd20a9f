"""The sparse pseudo-image: features on active BEV sites plus their integer coordinates.

Frame: pseudo-image grid indices. ``coords`` rows are ``[batch, iy, ix]`` with ``iy`` in ``[0, H)`` and ``ix`` in
``[0, W)``, i.e. the same ``(row, column)`` order as the dense canvas ``(B, C, H, W)`` that ``dense()`` produces.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from detector.sparse.indices import SiteLookup, flat_keys
from detector.sparse.phases import phase
from detector.sparse.workspace import Workspace, inference_workspace


class SparseTensor:
    """Features on the active sites of a batch of 2-D grids (spconv's ``SparseConvTensor``, without global state).

    Args:
        features: ``(N, C)`` float, one row per active site.
        coords: ``(N, 3)`` int64 ``[batch, iy, ix]``; rows must be unique (one row per site). Any row order is allowed;
            the ops here keep the order they are given and produce rows sorted by ``(batch, iy, ix)``.
        spatial_shape: ``(H, W)`` of the grid.
        batch_size: ``B``; batch items with no active site are allowed.
        cache: neighbour tables shared between tensors on the same sites (keyed by ``indice_key``); leave ``None``.
        workspace: buffers reused from frame to frame at inference (``detector.sparse.workspace``); the layers that
            get this tensor pass it on to their outputs. ``None``: every op allocates, as in training.
        origin: what made this site set (the layer, or the model for its input): the workspace keys this set's site
            lookup by it, so it must be the same object every frame and unique among the sets alive at once.

    A tensor is never edited in place: ``replace_feature`` returns a new tensor on the same sites that shares the
    cache, so a block builds its neighbour table once and every SubM conv of the block reuses it.
    """

    def __init__(
        self,
        features: Tensor,
        coords: Tensor,
        spatial_shape: tuple[int, int] | list[int],
        batch_size: int,
        cache: dict[Any, Any] | None = None,
        workspace: Workspace | None = None,
        origin: object | None = None,
    ) -> None:
        if features.dim() != 2:
            raise ValueError(f"features must be (N, C), got shape {tuple(features.shape)}")
        if coords.dim() != 2 or coords.shape[1] != 3 or coords.shape[0] != features.shape[0]:
            raise ValueError(
                f"coords must be (N, 3) with N = {features.shape[0]} rows, got shape {tuple(coords.shape)}"
            )
        if coords.dtype != torch.int64:
            raise ValueError(f"coords must be int64, got {coords.dtype}")
        if len(spatial_shape) != 2:
            raise ValueError(f"spatial_shape must be (H, W), got {spatial_shape}")
        self.features = features
        self.coords = coords
        self.spatial_shape: tuple[int, int] = (int(spatial_shape[0]), int(spatial_shape[1]))
        self.batch_size = int(batch_size)
        self.cache: dict[Any, Any] = {} if cache is None else cache
        self.workspace = workspace
        if origin is not None:
            self.cache["origin"] = origin

    # -- construction --------------------------------------------------------------------------------------------
    @classmethod
    def from_dense(cls, x: Tensor, mask: Tensor | None = None) -> SparseTensor:
        """Sparse view of a dense canvas.

        Args:
            x: ``(B, C, H, W)``.
            mask: ``(B, H, W)`` bool active sites; default: sites where any channel is non-zero.
        """
        if x.dim() != 4:
            raise ValueError(f"x must be (B, C, H, W), got shape {tuple(x.shape)}")
        if mask is None:
            mask = (x != 0).any(dim=1)
        coords = mask.nonzero()  # (N, 3) [b, y, x], sorted row-major
        feats = x[coords[:, 0], :, coords[:, 1], coords[:, 2]]
        return cls(feats, coords, (x.shape[2], x.shape[3]), x.shape[0])

    def replace_feature(self, features: Tensor) -> SparseTensor:
        """New tensor on the same sites (same coords, shape and neighbour-table cache) with ``features`` (N, C')."""
        if features.shape[0] != self.features.shape[0]:
            raise ValueError(f"replace_feature needs {self.features.shape[0]} rows, got {features.shape[0]}")
        return SparseTensor(features, self.coords, self.spatial_shape, self.batch_size, self.cache, self.workspace)

    # -- queries --------------------------------------------------------------------------------------------------
    @property
    def num_active(self) -> int:
        return int(self.coords.shape[0])

    def keys(self) -> Tensor:
        """``(N,)`` int64 flat site keys ``(b * H + iy) * W + ix`` (cached)."""
        k = self.cache.get("keys")
        if k is None:
            with phase("table"):
                k = flat_keys(self.coords, self.spatial_shape)
            self.cache["keys"] = k
        return k

    def lookup(self) -> SiteLookup:
        """Site → row map of this tensor's active set (built once, cached with the neighbour tables)."""
        lk = self.cache.get("lookup")
        if lk is None:
            ws = inference_workspace(self.workspace)
            origin = self.cache.get("origin")
            with phase("table"):
                lk = SiteLookup(self.keys(), self.spatial_shape, self.batch_size,
                                workspace=None if origin is None else ws, owner=origin)
            self.cache["lookup"] = lk
        return lk

    def active_mask(self) -> Tensor:
        """``(B, H, W)`` bool, True on active sites."""
        h, w = self.spatial_shape
        ws, origin = inference_workspace(self.workspace), self.cache.get("origin")
        keys = self.keys()
        with phase("scatter"):
            if ws is not None and origin is not None:
                ones = torch.ones(1, dtype=torch.bool, device=keys.device).expand(keys.numel())
                return ws.scatter(origin, "mask", (self.batch_size * h * w,), (keys,), ones, fill=False).view(
                    self.batch_size, h, w)
            m = torch.zeros(self.batch_size * h * w, dtype=torch.bool, device=self.coords.device)
            m[keys] = True
            return m.view(self.batch_size, h, w)

    def dense(self, channels_first: bool = True) -> Tensor:
        """Zero-filled canvas ``(B, C, H, W)`` (or ``(B, H, W, C)`` with ``channels_first=False``).

        Differentiable w.r.t. ``features`` (a scatter whose backward is a gather, so it is deterministic).
        """
        return scatter_to_dense(self.features, self.keys(), self.spatial_shape, self.batch_size, channels_first)

    def __repr__(self) -> str:
        return (
            f"SparseTensor(N={self.num_active}, C={self.features.shape[1]}, spatial_shape={self.spatial_shape}, "
            f"batch_size={self.batch_size}, dtype={self.features.dtype}, device={self.features.device})"
        )


def scatter_to_dense(
    features: Tensor,
    keys: Tensor,
    spatial_shape: tuple[int, int],
    batch_size: int,
    channels_first: bool = True,
    workspace: Workspace | None = None,
    owner: object | None = None,
) -> Tensor:
    """Scatter ``(N, C)`` rows at flat site keys ``(b * H + iy) * W + ix`` into a zero canvas.

    Returns ``(B, C, H, W)`` (contiguous, the layout ``nn.Conv2d`` expects) or ``(B, H, W, C)``. The channels-first
    scatter writes the transposed ``(C, N)`` features straight to their strided positions, so no transposed copy of
    the big canvas is made. With a ``workspace`` (inference) the canvas is ``owner``'s reused buffer, zero but for
    this call's sites (:meth:`Workspace.scatter`), valid until ``owner`` scatters again; keys must then be unique.
    """
    with phase("scatter"):
        return _scatter_to_dense(features, keys, spatial_shape, batch_size, channels_first, workspace, owner)


def _scatter_to_dense(features: Tensor, keys: Tensor, spatial_shape: tuple[int, int], batch_size: int,
                      channels_first: bool, workspace: Workspace | None, owner: object | None) -> Tensor:
    h, w = spatial_shape
    n, c = features.shape
    hw = h * w
    if workspace is not None:
        if channels_first:  # (B, C, H*W) viewed as (B, H*W, C): index (b, hw) takes a site's C values
            b = torch.div(keys, hw, rounding_mode="floor")
            buf = workspace.scatter(owner, "canvas_nchw", (batch_size, c, hw), (b, keys - b * hw), features,
                                    dims=(0, 2, 1))
            return buf.view(batch_size, c, h, w)
        buf = workspace.scatter(owner, "canvas_nhwc", (batch_size * hw, c), (keys,), features)
        return buf.view(batch_size, h, w, c)
    if not channels_first:
        out = features.new_zeros(batch_size * hw, c)
        return out.index_put_((keys,), features).view(batch_size, h, w, c)
    b = torch.div(keys, hw, rounding_mode="floor")
    base = b * (c * hw) + (keys - b * hw)  # flat offset of channel 0 of each site
    # Channel-major order: all N sites of channel 0, then of channel 1, ... Consecutive writes then stay inside one
    # (H, W) plane (a few hundred KB) instead of jumping a whole plane per write (site-major order touches C pages
    # per site): measured 3x faster on the 384-channel Matterport map (docs/sparse.md).
    idx = torch.arange(c, device=keys.device, dtype=torch.int64)[:, None] * hw + base[None, :]  # (C, N)
    # in-place scatter_ into a fresh zero buffer: the out-of-place scatter would copy the whole canvas once more
    out = features.new_zeros(batch_size * c * hw)
    return out.scatter_(0, idx.reshape(-1), features.t().reshape(-1)).view(batch_size, c, h, w)
