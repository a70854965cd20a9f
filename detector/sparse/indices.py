"""Neighbour tables ("rulebooks") for sparse 2-D convolution on a batch of grids.

All functions are pure tensor code (no Python loop over sites), run on the device of their inputs, and are
deterministic. Sites are grid indices ``[batch, iy, ix]`` (see ``detector.sparse.tensor``); a site's flat key is
``(b * H + iy) * W + ix``, which orders sites exactly like a row-major ``(B, H, W)`` canvas.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from detector.sparse.workspace import Workspace

# A dense key -> row grid costs 4 bytes per cell (int32) but makes each query one gather; above this many cells
# (32 MiB) the lookup switches to sorted keys + searchsorted, whose memory is proportional to the active sites only.
DENSE_GRID_MAX_CELLS = 1 << 23

Downsample = Literal["floor", "reference_quirk"]


def flat_keys(coords: Tensor, spatial_shape: tuple[int, int]) -> Tensor:
    """``(N, 3)`` int64 ``[b, iy, ix]`` → ``(N,)`` int64 keys ``(b * H + iy) * W + ix``."""
    h, w = spatial_shape
    return (coords[:, 0] * h + coords[:, 1]) * w + coords[:, 2]


def keys_to_coords(keys: Tensor, spatial_shape: tuple[int, int]) -> Tensor:
    """Inverse of ``flat_keys``: ``(N,)`` keys → ``(N, 3)`` int64 ``[b, iy, ix]``."""
    h, w = spatial_shape
    bx = torch.div(keys, w, rounding_mode="floor")
    x = keys - bx * w
    b = torch.div(bx, h, rounding_mode="floor")
    y = bx - b * h
    return torch.stack([b, y, x], dim=1)


class SiteLookup:
    """Map from site keys to the row of that site in a tensor's feature matrix (``-1`` = inactive).

    Args:
        keys: ``(N,)`` int64 unique flat keys of the active sites, in row order.
        spatial_shape: ``(H, W)``.
        batch_size: ``B``.
        mode: ``"grid"`` (a dense ``B*H*W`` int32 map), ``"sorted"`` (sorted keys + ``searchsorted``) or ``"auto"``
            (grid up to ``DENSE_GRID_MAX_CELLS`` cells).
        workspace, owner: keep the grid in ``owner``'s workspace buffer (inference), where only the cells set last
            time are reset; the grid is then valid until ``owner`` builds its next lookup.
    """

    def __init__(
        self,
        keys: Tensor,
        spatial_shape: tuple[int, int],
        batch_size: int,
        mode: Literal["auto", "grid", "sorted"] = "auto",
        workspace: Workspace | None = None,
        owner: object | None = None,
    ) -> None:
        cells = batch_size * spatial_shape[0] * spatial_shape[1]
        if mode == "auto":
            mode = "grid" if cells <= DENSE_GRID_MAX_CELLS else "sorted"
        self.mode = mode
        self.num_cells = cells
        n = keys.shape[0]
        if mode == "grid":
            # int32 halves the memory traffic of building and reading the map; rows are < 2**31 in any real batch.
            rows = torch.arange(n, dtype=torch.int32, device=keys.device)
            if workspace is not None:
                self.grid = workspace.scatter(owner, "lookup", (cells,), (keys,), rows, fill=-1)
            else:
                self.grid = torch.full((cells,), -1, dtype=torch.int32, device=keys.device)
                self.grid[keys] = rows
        elif mode == "sorted":
            self.sorted_keys, self.order = torch.sort(keys)
        else:
            raise ValueError(f"unknown lookup mode {mode!r}")

    def query(self, keys: Tensor, valid: Tensor | None = None) -> Tensor:
        """Rows of ``keys`` (any shape, int64), ``-1`` where the site is inactive or ``valid`` is False."""
        if valid is not None:
            keys = torch.where(valid, keys, torch.zeros_like(keys))
        if self.mode == "grid":
            rows = self.grid[keys].long()
        else:
            if self.sorted_keys.numel() == 0:
                return torch.full_like(keys, -1)
            pos = torch.searchsorted(self.sorted_keys, keys).clamp_(max=self.sorted_keys.numel() - 1)
            hit = self.sorted_keys[pos] == keys
            rows = torch.where(hit, self.order[pos], torch.full_like(keys, -1))
        if valid is not None:
            rows = torch.where(valid, rows, torch.full_like(rows, -1))
        return rows


@dataclass
class SubMTable:
    """Neighbour table of a submanifold conv on one active set.

    ``table[i, k]`` is the row of the neighbour of site ``i`` at kernel offset ``k = ky * ks + kx`` (the position in a
    ``Conv2d`` weight ``[:, :, ky, kx]``; the neighbour sits at ``(iy + ky - ks//2, ix + kx - ks//2)``), or ``-1``.
    """

    table: Tensor  # (N, K) int64
    kernel_size: int
    _padded: Tensor | None = None
    _fill: float | None = None
    _pairs: tuple[Tensor, Tensor, list[int]] | None = None

    @property
    def padded(self) -> Tensor:
        """``(N * K,)`` table with ``-1`` replaced by ``N`` (the index of an appended zero row)."""
        if self._padded is None:
            n = self.table.shape[0]
            self._padded = torch.where(self.table >= 0, self.table, torch.full_like(self.table, n)).reshape(-1)
        return self._padded

    @property
    def fill(self) -> float:
        """Fraction of (site, offset) pairs whose neighbour is active (1.0 = every site has all K neighbours)."""
        if self._fill is None:
            n, k = self.table.shape
            self._fill = float((self.table >= 0).sum()) / max(1, n * k)
        return self._fill

    def pairs(self) -> tuple[Tensor, Tensor, list[int]]:
        """Rulebook form: ``(in_rows, out_rows, counts)`` grouped by offset (centre excluded), ``counts[k]`` pairs each.

        ``in_rows``/``out_rows`` are ``(P,)`` int64; pair ``j`` says input row ``in_rows[j]`` feeds output row
        ``out_rows[j]`` through the weight of its offset group.
        """
        if self._pairs is None:
            n, k = self.table.shape
            centre = k // 2
            t = torch.cat([self.table[:, :centre], self.table[:, centre + 1 :]], dim=1).t()  # (K-1, N)
            valid = t >= 0
            out_rows = torch.arange(n, device=t.device).expand(k - 1, n)[valid]
            in_rows = t[valid]
            counts = valid.sum(dim=1).tolist()
            self._pairs = (in_rows, out_rows, counts)
        return self._pairs


def subm_table(coords: Tensor, spatial_shape: tuple[int, int], lookup: SiteLookup, kernel_size: int) -> SubMTable:
    """Neighbour table of a ``kernel_size`` x ``kernel_size`` SubM conv on the active sites ``coords`` (N, 3).

    Neighbours outside the grid count as inactive, exactly like the zero padding of a dense ``conv2d`` with
    ``padding = kernel_size // 2``.
    """
    if kernel_size % 2 != 1 or kernel_size < 1:
        raise ValueError(f"SubM kernel_size must be odd and positive, got {kernel_size}")
    h, w = spatial_shape
    r = kernel_size // 2
    d = torch.arange(-r, r + 1, device=coords.device, dtype=torch.int64)
    dy = d.repeat_interleave(kernel_size)  # offset k = ky * ks + kx  ->  (ky - r, kx - r)
    dx = d.repeat(kernel_size)
    ny = coords[:, 1:2] + dy[None, :]  # (N, K)
    nx = coords[:, 2:3] + dx[None, :]
    valid = (ny >= 0) & (ny < h) & (nx >= 0) & (nx < w)
    keys = (coords[:, 0:1] * h + ny) * w + nx
    return SubMTable(lookup.query(keys, valid), kernel_size)


@dataclass
class DownTable:
    """Rulebook of a strided down-conv: input row ``in_rows[j]`` feeds output row ``out_rows[j]`` through kernel slot
    ``slots[j]``.

    Non-overlapping (kernel = stride = s, :func:`down_table`): one pair per input, slot ``(iy % s) * s + ix % s``; each
    (output, slot) pair occurs at most once, so the scatter needs no accumulation. Wide (odd kernel k > s,
    :func:`wide_down_table`): slot ``ky * k + kx``, several pairs per input.
    """

    out_coords: Tensor  # (M, 3) int64, sorted by key
    out_shape: tuple[int, int]
    in_rows: Tensor  # (P,) int64
    out_rows: Tensor  # (P,) int64
    slots: Tensor  # (P,) int64

    def gather_index(self, num_inputs: int, kernel_cells: int) -> Tensor:
        """The GEMM form's table: ``(M * kernel_cells,)`` int64, entry ``m * kernel_cells + slot`` = the input row
        that output ``m`` takes through that slot, or ``num_inputs`` (the appended zero row) where none does.

        Gathering these rows of the inputs padded with one zero row gives the ``(M, kernel_cells * C)`` matrix whose
        product with the ``(kernel_cells * C, O)`` weight is the conv (``detector.sparse.conv.gather_gemm``).
        """
        m = self.out_coords.shape[0]
        index = torch.full((m * kernel_cells,), num_inputs, dtype=torch.int64, device=self.in_rows.device)
        return index.index_put_((self.out_rows * kernel_cells + self.slots,), self.in_rows)

    def fill(self, kernel_cells: int) -> float:
        """Fraction of the ``M * kernel_cells`` (output, slot) cells that an input feeds."""
        return self.in_rows.numel() / max(1, self.out_coords.shape[0] * kernel_cells)


def down_table(
    coords: Tensor, spatial_shape: tuple[int, int], stride: int, downsample: Downsample = "floor"
) -> DownTable:
    """Output sites and rulebook of a ``stride`` x ``stride``, stride-``stride`` sparse conv.

    ``"floor"``: outputs = ``unique(floor(c / s))``; every input lands in exactly one output (inputs past the last
    full window, which a dense ``conv2d`` ignores too, are dropped). Output shape ``(H // s, W // s)``.

    ``"reference_quirk"`` (s = 2 in the reference): MinkowskiEngine's ``expand_coordinates=True`` output set,
    ``unique(ceil(c / s))`` per axis (an input at a multiple of ``s`` keeps its site, any other rounds up), while each
    output still gathers its floor window ``s q + [0, s)^2``. An input contributes only if its floor parent happens to
    be in that set. Raises ``ValueError`` if a rounded-up site falls past the grid (the reference pads its grid so
    that this cannot happen; ME's ``.dense()`` raises there too).
    """
    h, w = spatial_shape
    s = stride
    ho, wo = h // s, w // s
    b, y, x = coords[:, 0], coords[:, 1], coords[:, 2]
    py = torch.div(y, s, rounding_mode="floor")
    px = torch.div(x, s, rounding_mode="floor")
    slots = (y - py * s) * s + (x - px * s)
    parent_keys = (b * ho + py) * wo + px
    inside = (py < ho) & (px < wo)
    rows = torch.arange(coords.shape[0], device=coords.device)
    if downsample == "floor":
        keep = rows[inside]
        out_keys, inverse = torch.unique(parent_keys[keep], sorted=True, return_inverse=True)
        return DownTable(keys_to_coords(out_keys, (ho, wo)), (ho, wo), keep, inverse, slots[keep])
    if downsample == "reference_quirk":
        qy = torch.div(y + (s - 1), s, rounding_mode="floor")
        qx = torch.div(x + (s - 1), s, rounding_mode="floor")
        if bool(((qy >= ho) | (qx >= wo)).any()):
            raise ValueError(
                f"reference_quirk downsampling rounds a site past the {ho}x{wo} output grid; pad the input grid "
                "(the reference uses 768x512 / 504x440 for 760x500 / 496x432 data)"
            )
        out_keys = torch.unique((b * ho + qy) * wo + qx, sorted=True)
        # sorted mode: the batch size is not needed and the set is small
        out_lookup = SiteLookup(out_keys, (ho, wo), 1, mode="sorted")
        out_rows = out_lookup.query(parent_keys, inside)
        hit = out_rows >= 0
        return DownTable(keys_to_coords(out_keys, (ho, wo)), (ho, wo), rows[hit], out_rows[hit], slots[hit])
    raise ValueError(f"unknown downsample mode {downsample!r} (expected 'floor' or 'reference_quirk')")


def wide_down_table(coords: Tensor, spatial_shape: tuple[int, int], kernel_size: int, stride: int) -> DownTable:
    """Output sites and rulebook of a ``k`` x ``k`` stride-``s`` sparse conv with ``padding = k // 2`` (odd ``k > s``).

    The output set is every site of the ``(H // s, W // s)`` grid whose ``k`` x ``k`` window (rows ``s q - k//2 ..
    s q + k//2``) holds an active input: exactly the sites where ``F.conv2d(dense, w, stride=s, padding=k // 2)`` can
    be non-zero. That is MinkowskiEngine's ``expand_coordinates=True`` set for an odd kernel (its output sites are the
    stride-aligned ``p + offset``, and an output gathers the same symmetric window), restricted to the grid. An input
    meets up to ``ceil(k / s)^2`` outputs: pair ``j`` says input row ``in_rows[j]`` feeds output row ``out_rows[j]``
    through weight tap ``slots[j] = ky * k + kx``.
    """
    if kernel_size % 2 != 1 or kernel_size <= stride:
        raise ValueError(f"wide down-conv needs an odd kernel_size > stride, got {kernel_size} and stride {stride}")
    h, w = spatial_shape
    s, k, p = stride, kernel_size, kernel_size // 2
    ho, wo = h // s, w // s
    d = torch.arange(k, device=coords.device, dtype=torch.int64)
    # input c reaches output q through tap d when s * q - p + d == c, i.e. s * q = c + p - d
    sy = coords[:, 1:2] + p - d[None, :]  # (N, k) candidates s * q_y per tap row
    sx = coords[:, 2:3] + p - d[None, :]
    vy = (sy % s == 0) & (sy >= 0) & (sy < s * ho)
    vx = (sx % s == 0) & (sx >= 0) & (sx < s * wo)
    rows, ty, tx = torch.nonzero(vy[:, :, None] & vx[:, None, :], as_tuple=True)
    oy = torch.div(sy[rows, ty], s, rounding_mode="floor")
    ox = torch.div(sx[rows, tx], s, rounding_mode="floor")
    out_keys, out_rows = torch.unique((coords[rows, 0] * ho + oy) * wo + ox, sorted=True, return_inverse=True)
    return DownTable(keys_to_coords(out_keys, (ho, wo)), (ho, wo), rows, out_rows, ty * k + tx)


@dataclass
class UpTable:
    """Rulebook of a transposed conv (kernel = stride = s) evaluated on a target active set.

    Target row ``i`` takes kernel slot ``slots[i] = (iy % s) * s + ix % s`` of its parent ``floor(c / s)``, which is row
    ``parent_rows[i]`` of the coarse tensor or ``-1`` when the parent is inactive (the output there is zero).
    """

    parent_rows: Tensor  # (N_target,) int64
    slots: Tensor  # (N_target,) int64

    def gather_index(self, num_coarse: int, stride: int) -> Tensor:
        """The GEMM form's table: ``(N_target,)`` int64 row ``parent * stride**2 + slot`` of the ``(num_coarse *
        stride**2, O)`` products of every coarse site with every slot's weight, or ``num_coarse * stride**2`` (an
        appended zero row) for a target without an active parent."""
        s2 = stride * stride
        rows = self.parent_rows * s2 + self.slots
        return torch.where(self.parent_rows >= 0, rows, torch.full_like(rows, num_coarse * s2))

    def by_slot(self, stride: int) -> tuple[Tensor, Tensor, list[int]]:
        """Targets with an active parent, grouped by slot: ``(rows, parents, counts)``.

        ``rows`` (V,) are target rows and ``parents`` (V,) their parent rows, ordered by slot (stable, so by target row
        within a slot); ``counts[k]`` of them (``stride**2`` entries) use slot ``k``.
        """
        has_parent = self.parent_rows >= 0
        rows = torch.nonzero(has_parent).squeeze(1)
        slots = self.slots[rows]
        order = torch.argsort(slots, stable=True)
        rows = rows[order]
        counts = torch.bincount(slots, minlength=stride * stride).tolist()
        return rows, self.parent_rows[rows], counts


def up_table(target_coords: Tensor, coarse_shape: tuple[int, int], coarse_lookup: SiteLookup, stride: int) -> UpTable:
    """Parents and kernel slots of the target sites ``(N, 3)`` under a stride-``stride`` transposed conv."""
    s = stride
    hc, wc = coarse_shape
    b, y, x = target_coords[:, 0], target_coords[:, 1], target_coords[:, 2]
    py = torch.div(y, s, rounding_mode="floor")
    px = torch.div(x, s, rounding_mode="floor")
    slots = (y - py * s) * s + (x - px * s)
    inside = (py < hc) & (px < wc)
    parent_rows = coarse_lookup.query((b * hc + py) * wc + px, inside)
    return UpTable(parent_rows, slots)
