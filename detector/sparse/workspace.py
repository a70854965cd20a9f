"""Buffers that inference reuses from frame to frame, so a steady stream of frames allocates (and page-faults) nothing.

glibc serves an allocation above its mmap threshold (at most 32 MiB) with a fresh ``mmap`` and unmaps it on ``free``,
so every frame that builds a 151 MB canvas pays ~37,000 page faults for it, and every freed heap top above the trim
threshold goes back to the kernel too. A :class:`Workspace` keeps each buffer alive between frames instead: a layer
asks for ``(owner, name)`` with a shape and gets the same memory as last frame whenever it fits (it grows, with
headroom, when a frame needs more). Nothing is global: a model owns its workspace (``PointPillars.workspace``) and
hands it to its layers (through ``SparseTensor.workspace`` in the sparse backbone, as an argument elsewhere).

Only inference uses it (:func:`inference_workspace`: autograd off): a training forward keeps every activation for the
backward, so it allocates as before. **Aliasing:** a tensor a layer returns from the workspace is overwritten when
that layer runs again, so a caller that keeps outputs of one frame while running the next must ``clone()`` them (or
run without a workspace, the default of a model).

:meth:`Workspace.scatter` keeps a canvas that is ``fill`` everywhere but at the rows written last frame: the next frame
resets those rows and writes its own, instead of refilling the whole canvas (a fresh zero 151 MB neck canvas is
37k page faults and a full memset; its ~1,500 rows cost microseconds). Measured together with the other buffers:
the Matterport sparse backbone 94.5 → 32.7 ms per frame, 1 thread, default allocator (docs/sparse.md).
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

#: A buffer that must grow is allocated this much larger than the frame needs, so frames of slowly rising size do not
#: reallocate every time.
GROWTH = 1.25


def inference_workspace(workspace: Workspace | None) -> Workspace | None:
    """``workspace`` when autograd is off (``torch.no_grad`` / ``inference_mode``), else None (training allocates)."""
    return workspace if workspace is not None and not torch.is_grad_enabled() else None


@dataclass
class _Canvas:
    """State of one :meth:`Workspace.scatter` canvas: the buffer view, the fill it holds, the rows written last."""

    view: Tensor
    fill: Tensor
    dirty: tuple[Tensor, ...]


class Workspace:
    """Reusable buffers keyed by ``(owner, name)``, one per dtype and device (owner: the layer, e.g. ``self``)."""

    def __init__(self) -> None:
        self._flat: dict[tuple[Hashable, ...], Tensor] = {}
        self._views: dict[tuple[Hashable, ...], Tensor] = {}  # the last view handed out per key (same shape: reused)
        self._canvases: dict[tuple[Hashable, ...], _Canvas] = {}

    def take(self, owner: Hashable, name: str, shape: Sequence[int], dtype: torch.dtype,
             device: torch.device | str) -> Tensor:
        """A contiguous tensor of ``shape``, contents unspecified: the same memory as the previous call with this
        ``(owner, name)``, dtype and device whenever it fits."""
        shape = tuple(int(s) for s in shape)
        key = (owner, name, dtype, str(device))
        view = self._views.get(key)
        if view is not None and view.shape == shape:
            return view  # the same buffer and shape as last time: no new view (a frame asks for ~100 of them)
        numel = 1
        for s in shape:
            numel *= s
        flat = self._flat.get(key)
        if flat is None or flat.numel() < numel:
            flat = torch.empty(max(numel, int(GROWTH * numel)), dtype=dtype, device=device)
            self._flat[key] = flat
        view = flat[:numel].view(shape)
        self._views[key] = view
        return view

    def scatter(self, owner: Hashable, name: str, shape: Sequence[int], index: tuple[Tensor, ...], values: Tensor,
                fill: float | Tensor = 0.0, dims: Sequence[int] | None = None) -> Tensor:
        """A buffer of ``shape`` (``values.dtype`` / device) equal to ``fill`` everywhere except at ``view[index] =
        values``, where ``view`` is the buffer permuted by ``dims`` (default: the buffer itself).

        ``index`` is a tuple of int64 index tensors for the leading dims of ``view`` (as in ``view[index] = values``,
        so ``values`` and ``fill`` broadcast against the rest). The rows written last time are reset to ``fill``
        first, so a frame costs its own rows, not the whole canvas; a changed ``shape``, ``fill``, dtype or device
        refills it once. Returns the buffer in ``shape`` (not permuted).
        """
        fill_t = torch.as_tensor(fill, dtype=values.dtype, device=values.device)
        buf = self.take(owner, name + ".canvas", shape, values.dtype, values.device)
        view = buf if dims is None else buf.permute(*dims)
        key = (owner, name, values.dtype, values.device)
        state = self._canvases.get(key)
        if (state is None or state.view.data_ptr() != view.data_ptr() or state.view.shape != view.shape
                or state.view.stride() != view.stride() or not torch.equal(state.fill, fill_t)):
            view.copy_(fill_t.expand_as(view))
        elif state.dirty[0].numel():
            view.index_put_(state.dirty, fill_t)
        view.index_put_(index, values)
        dirty = tuple(self._keep(owner, f"{name}.dirty{i}", ix) for i, ix in enumerate(index))
        self._canvases[key] = _Canvas(view, fill_t.clone(), dirty)
        return buf

    def _keep(self, owner: Hashable, name: str, t: Tensor) -> Tensor:
        """A workspace copy of ``t`` (index tensors are rebuilt every frame, possibly in reused memory)."""
        out = self.take(owner, name, t.shape, t.dtype, t.device)
        return out.copy_(t)

    def nbytes(self) -> int:
        """Bytes held by every buffer (for reports)."""
        return sum(t.numel() * t.element_size() for t in self._flat.values())
