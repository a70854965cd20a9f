"""Exact multiply-accumulate (MAC) counts of the dense and sparse backbones + necks, beside the paper's Table I.

**What Table I counts.** Its unit is a *convolution*: one ``k x k`` kernel applied for one (input channel, output
channel) pair, i.e. ``k^2`` MACs. Regular convs are counted per output site, transposed convs per input site, and the
sparse 2x2 down-conv per *active input* (each input meets exactly one kernel tap, so ``N_in * C_in * C_out`` MACs =
``N_in * C_in * C_out / 4`` convolutions: the ``D / 4`` term). With ``C = 64``, ``H x W`` the padded pseudo-image and
``D`` its density, the dense rows (3x3: ``15/4 C^2 HW``, 1x1/2x2/4x4 transposed: ``1/2, 1/4, 1/8 C^2 HW``) are exact,
and the sparse rows bound the active sites after block i by ``min(D HW, HW / 4^i)`` (each input lands in one output).
:func:`table1` transcribes the table literally; :func:`layer_bound` is the same bound per layer for any channels.

**What we count.** Per layer, from the real modules (forward hooks) on each frame's real pillar sites:

- ``dense``: the dense backbone + neck, ``outputs * C_in * C_out * k^2`` (transposed: ``inputs * ...``), by shape
  arithmetic over the built modules, so it costs nothing.
- ``sparse`` (exact): the *rulebook* count, ``active (input, output, tap) triples * C_in * C_out``, from the sparse
  backbone's own index machinery (``detector.sparse.indices``: the SubM neighbour tables, ``floor(c / 2)`` down
  tables, the transposed conv's parent lookup on the block-1 set). This is what a gather-scatter sparse engine must
  multiply; it is never above the bound (tested on real-ish and uniform-random sites).
- ``sparse_computed``: what ``detector.sparse`` actually multiplies, zero rows included, in the form each layer
  runs in the counting context (float32 inference: ``detector.sparse.conv.subm_algorithm`` / ``up_algorithm``, the
  engine's own choice): the one-GEMM SubM form does all ``k^2`` taps of every site (in oneDNN it is taken at any
  fill), the 2x2 down-conv multiplies an ``(M, 4 C_in)`` buffer with empty slots, the transposed conv's GEMM form
  multiplies every coarse site by all ``s^2`` slots' weights (``M s^2 C_in C_out``), its rulebook form only the
  (target, parent tap) pairs. The rows oneDNN's bucketing adds (``detector.ops.gemm.bucket_rows``) are not counted.
  This one *can* exceed the bound (the down-conv, the transposed GEMM form).

Conv types are ``"3x3 conv"`` (dense 3x3 of stride 1 and 2 together, and SubM 3x3, as the table), ``"2x2 conv"``
(sparse down), ``"9x9 conv"`` (Sparse+WideConv), ``"1x1 convT"``, ``"2x2 convT"``, ``"4x4 convT"``; blocks are
``block1..3`` (backbone) and ``up1..3`` (neck levels). The head (1x1 convs) is outside Table I and reported apart.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from detector.config import ExperimentConfig, ModelConfig, load_experiment
from detector.models import build_model
from detector.sparse import SparseConv2d, SparseConvTranspose2d, SparseTensor, SubMConv2d
from detector.sparse.conv import GEMM_MIN_FILL, subm_algorithm, transposed_matrix, up_algorithm
from detector.sparse.indices import down_table, up_table, wide_down_table
from mpchair.paper import (
    KITTI_DENSITY,
    KITTI_FEWER_CONVOLUTIONS,
    MATTERPORT_CHAIR_DENSITY,
    MATTERPORT_CHAIR_FEWER_CONVOLUTIONS,
)

#: Table I's rows, in its order.
TABLE1_TYPES: tuple[str, ...] = ("3x3 conv", "2x2 conv", "1x1 convT", "2x2 convT", "4x4 convT")


@dataclass
class LayerCount:
    """MACs of one conv layer on one frame (batch 1).

    ``grid``: ``(h, w)`` of the layer's input; ``in_sites`` / ``out_sites``: active sites in / out (all cells for
    dense layers); ``pairs``: active (input, output, tap) triples (sparse) or ``outputs * k^2`` (dense conv) /
    ``inputs * k^2`` (dense transposed); ``macs = pairs * c_in * c_out``; ``bound``: the Table I bound for this
    layer in MACs (``= macs`` for a dense layer).
    """

    name: str
    conv_type: str
    block: str
    kind: str  # dense_conv | dense_convT | subm | sparse_down | sparse_convT
    kernel: int
    c_in: int
    c_out: int
    grid: tuple[int, int]
    in_sites: int
    out_sites: int
    pairs: int
    macs: int
    macs_computed: int
    bound: int

    @property
    def convolutions(self) -> float:
        """The paper's unit: MACs / k^2."""
        return self.macs / self.kernel**2


def _block_of(name: str) -> str:
    m = re.search(r"deblocks\.(\d+)", name)
    if m:
        return f"up{int(m.group(1)) + 1}"
    m = re.search(r"blocks\.(\d+)", name)
    return f"block{int(m.group(1)) + 1}" if m else name


def layer_bound(
    kind: str, kernel: int, c_in: int, c_out: int, grid: tuple[int, int], n0: int, stride: int | None = None
) -> int:
    """Table I's bound for one sparse layer, in MACs; ``n0`` = active input pillars (``D * H * W``).

    Active sites on any grid are at most ``min(n0, cells)`` (every layer maps each active site to one site of the next
    grid). SubM: ``k^2 C_in C_out`` per active site; sparse down (kernel = stride): ``C_in C_out`` per active *input*;
    transposed: ``s^2 C_in C_out`` per active coarse input. A wide down-conv (odd kernel k > stride s, an ablation
    outside Table I, whose outputs grow the active set) meets up to ``ceil(k / s)^2`` outputs per input, so its
    bound is that many times ``C_in C_out`` per active input (the active-site cap above does not hold after it).
    """
    cells = grid[0] * grid[1]
    n = min(n0, cells)
    if kind == "subm":
        return kernel * kernel * c_in * c_out * n
    if kind == "sparse_down":
        s = kernel if stride is None else stride
        return math.ceil(kernel / s) ** 2 * c_in * c_out * n
    if kind == "sparse_convT":
        return kernel * kernel * c_in * c_out * n
    raise ValueError(f"no bound for layer kind {kind!r}")


class _Recorder:
    """Forward hooks that turn each conv call into a :class:`LayerCount`."""

    def __init__(self, n0: int) -> None:
        self.n0 = n0
        self.layers: list[LayerCount] = []

    def hook(self, name: str):
        def fn(module: nn.Module, args: tuple, output) -> None:
            self.layers.append(self.count(name, module, args, output))

        return fn

    def count(self, name: str, module: nn.Module, args: tuple, output) -> LayerCount:
        block = _block_of(name)
        if isinstance(module, SubMConv2d):
            x: SparseTensor = args[0]
            k = module.kernel_size
            table = module.table(x)  # (N, k*k) neighbour rows, -1 = inactive: exactly the rulebook
            n = x.num_active
            pairs = int((table.table >= 0).sum())
            gemm = subm_algorithm(module.algorithm, table, x.features, module.weight) == "gemm"
            computed = (n * k * k if gemm else pairs) * module.in_channels * module.out_channels
            macs = pairs * module.in_channels * module.out_channels
            return LayerCount(name, f"{k}x{k} conv", block, "subm", k, module.in_channels, module.out_channels,
                              x.spatial_shape, n, n, pairs, macs, computed,
                              layer_bound("subm", k, module.in_channels, module.out_channels, x.spatial_shape,
                                          self.n0))
        if isinstance(module, SparseConv2d):
            x = args[0]
            s, k = module.stride, module.kernel_size
            if k == s:
                t = down_table(x.coords, x.spatial_shape, s, module.downsample)
            else:
                t = wide_down_table(x.coords, x.spatial_shape, k, s)
            pairs = int(t.in_rows.numel())  # (input, output, tap) triples; k = s: each input meets one tap
            m = int(t.out_coords.shape[0])
            cc = module.in_channels * module.out_channels
            # one (M, k*k*C) matmul with empty slots (k = s: both forms; the wide conv's GEMM form), or the wide
            # conv's rulebook: per-tap products of the pairs only
            full = k == s or module.algorithm == "gemm" or (module.algorithm == "auto"
                                                            and t.fill(k * k) >= GEMM_MIN_FILL)
            computed = m * k * k * cc if full else pairs * cc
            return LayerCount(name, f"{k}x{k} conv", block, "sparse_down", k, module.in_channels,
                              module.out_channels, x.spatial_shape, x.num_active, m, pairs, pairs * cc, computed,
                              layer_bound("sparse_down", k, module.in_channels, module.out_channels, x.spatial_shape,
                                          self.n0, stride=s))
        if isinstance(module, SparseConvTranspose2d):
            x, target = args[0], args[1]
            s = module.stride
            cc = module.in_channels * module.out_channels
            if s == 1 and target.coords is x.coords:
                pairs = x.num_active
                computed = pairs * cc
            else:
                t = up_table(target.coords, x.spatial_shape, x.lookup(), s)
                pairs = int((t.parent_rows >= 0).sum())  # each target site takes one tap of its parent
                form = up_algorithm(module.algorithm, t, x.num_active, s, x.features,
                                    transposed_matrix(module.weight))
                # the GEMM form: every coarse site times every slot's weight; the rulebook: the products targets need
                computed = (x.num_active * s * s if form == "gemm" else pairs) * cc
            return LayerCount(name, f"{s}x{s} convT", block, "sparse_convT", s, module.in_channels,
                              module.out_channels, x.spatial_shape, x.num_active, target.num_active, pairs,
                              pairs * cc, computed,
                              layer_bound("sparse_convT", s, module.in_channels, module.out_channels,
                                          x.spatial_shape, self.n0))
        if isinstance(module, (nn.Conv2d, nn.ConvTranspose2d)):  # the dense tail of an ablation
            x = args[0]
            return _dense_layer(name, module, tuple(x.shape[-2:]), tuple(output.shape[-2:]))
        raise TypeError(f"not a conv layer: {type(module).__name__}")


_COUNTED = (SubMConv2d, SparseConv2d, SparseConvTranspose2d, nn.Conv2d, nn.ConvTranspose2d)


def _hooked(module: nn.Module, recorder: _Recorder, prefix: str) -> list:
    return [m.register_forward_hook(recorder.hook(f"{prefix}.{n}" if n else prefix))
            for n, m in module.named_modules() if isinstance(m, _COUNTED)]


def variants(cfg: ModelConfig) -> tuple[ModelConfig, ModelConfig]:
    """(dense, sparse) model configs for a config of either kind: the other one differs only in ``backbone``."""
    dense = replace(cfg, backbone="dense", head="dense")
    sparse = cfg if cfg.backbone != "dense" else replace(cfg, backbone="sparse")
    return dense, sparse


def _dense_layer(name: str, m: nn.Module, grid: tuple[int, int], out: tuple[int, int]) -> LayerCount:
    kh, kw = m.kernel_size
    transposed = isinstance(m, nn.ConvTranspose2d)
    sites = grid if transposed else out  # transposed convs apply the kernel per input site, convs per output site
    pairs = sites[0] * sites[1] * kh * kw
    macs = pairs * m.in_channels * m.out_channels // m.groups
    return LayerCount(name, f"{kh}x{kw} conv" + ("T" if transposed else ""), _block_of(name),
                      "dense_convT" if transposed else "dense_conv", kh, m.in_channels, m.out_channels, grid,
                      grid[0] * grid[1], out[0] * out[1], pairs, macs, macs, macs)


def _out_size(m: nn.Module, h: int, w: int) -> tuple[int, int]:
    """Output (h, w) of an ``nn.Conv2d`` / ``nn.ConvTranspose2d`` (PyTorch's size formulas)."""
    size = []
    for ax, n in enumerate((h, w)):
        k, s, p, d = m.kernel_size[ax], m.stride[ax], m.padding[ax], m.dilation[ax]
        if isinstance(m, nn.ConvTranspose2d):
            size.append((n - 1) * s - 2 * p + d * (k - 1) + m.output_padding[ax] + 1)
        else:
            size.append((n + 2 * p - d * (k - 1) - 1) // s + 1)
    return size[0], size[1]


def dense_counts(cfg: ModelConfig) -> list[LayerCount]:
    """Per-layer MACs of the dense backbone + neck of ``cfg``: outputs (transposed: inputs) x C_in x C_out x k^2.

    Pure shape arithmetic over the built modules (PyTorch's output-size formulas), so it costs nothing at any size.
    """
    with torch.random.fork_rng(devices=[]):
        model = build_model(replace(cfg, backbone="dense", head="dense"))
    layers: list[LayerCount] = []
    h, w = cfg.output_shape
    level_grids = []
    for i, block in enumerate(model.backbone.blocks):
        for j, m in enumerate(block):
            if isinstance(m, nn.Conv2d):
                ho, wo = _out_size(m, h, w)
                layers.append(_dense_layer(f"backbone.blocks.{i}.{j}", m, (h, w), (ho, wo)))
                h, w = ho, wo
        level_grids.append((h, w))
    for i, deblock in enumerate(model.neck.deblocks):
        for j, m in enumerate(deblock):
            if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
                layers.append(_dense_layer(f"neck.deblocks.{i}.{j}", m, level_grids[i], _out_size(m, *level_grids[i])))
    return layers


def sparse_counts(model: nn.Module, coords: torch.Tensor, cfg: ModelConfig) -> list[LayerCount]:
    """Per-layer MACs of the sparse backbone + neck ``model.backbone`` on the pillar sites ``coords`` (P, 3)
    ``[0, iy, ix]`` of one frame (features are zeros: the counts depend on the sites only)."""
    n0 = int(coords.shape[0])
    x = SparseTensor(torch.zeros(n0, cfg.pfn_channels), coords, cfg.output_shape, 1)
    rec = _Recorder(n0)
    handles = _hooked(model.backbone, rec, "backbone")
    try:
        with torch.no_grad():
            model.backbone(x)
    finally:
        for h in handles:
            h.remove()
    return rec.layers


def head_macs(cfg: ModelConfig, active_block1: int | None) -> int:
    """MACs of the 1x1 anchor head: every cell of the (ny/2, nx/2) map, or only ``active_block1`` sites (the exact
    sparse head)."""
    a = len(cfg.anchor_sizes) * len(cfg.anchor_rotations)
    c_out = a * cfg.num_classes + a * 7 + a * 2
    s = cfg.layer_strides[0] // cfg.upsample_strides[0]
    cells = (cfg.output_shape[0] // s) * (cfg.output_shape[1] // s)
    n = cells if active_block1 is None else active_block1
    return n * sum(cfg.neck_channels) * c_out


def table1(d: float, c: int, h: int, w: int) -> dict[str, dict[str, float]]:
    """The paper's Table I, literally, in its unit (convolutions = MACs / k^2): ``{row: {"dense", "bound"}}``."""
    chw = c * c * h * w
    return {
        "3x3 conv": {"dense": 15 / 4 * chw,
                     "bound": chw * (min(3 / 4, 3 * d) + min(5 / 4, 20 * d) + min(5 / 4, 80 * d))},
        "2x2 conv": {"dense": 0.0, "bound": chw * (d / 4 + min(1 / 8, d / 2) + min(1 / 8, 2 * d))},
        "1x1 convT": {"dense": chw / 2, "bound": chw * min(1 / 2, 2 * d)},
        "2x2 convT": {"dense": chw / 4, "bound": chw * min(1 / 4, 4 * d)},
        "4x4 convT": {"dense": chw / 8, "bound": chw * min(1 / 8, 8 * d)},
    }


def _kernel_of(conv_type: str) -> int:
    return int(conv_type.split("x", 1)[0])


def _aggregate(layers: Sequence[LayerCount], key: str) -> dict[str, dict[str, int]]:
    out: dict[str, dict[str, int]] = {}
    for lc in layers:
        g = out.setdefault(getattr(lc, key), {"macs": 0, "macs_computed": 0, "bound": 0})
        g["macs"] += lc.macs
        g["macs_computed"] += lc.macs_computed
        g["bound"] += lc.bound
    return out


def frame_counts(
    dense_layers: Sequence[LayerCount], sparse_layers: Sequence[LayerCount], n0: int, cfg: ModelConfig,
    active_block1: int, sparse_head: bool,
) -> dict:
    """One frame's comparison: per conv type, per block and in total (MACs), plus the paper-unit totals."""
    ny, nx = cfg.output_shape
    dt, st = _aggregate(dense_layers, "conv_type"), _aggregate(sparse_layers, "conv_type")
    db, sb = _aggregate(dense_layers, "block"), _aggregate(sparse_layers, "block")

    def merge(d: dict, s: dict, order: Sequence[str]) -> dict:
        keys = [k for k in order if k in d or k in s] + sorted(set(d) | set(s) - set(order))
        z = {"macs": 0, "macs_computed": 0, "bound": 0}
        return {k: {"dense": d.get(k, z)["macs"], "sparse": s.get(k, z)["macs"],
                    "sparse_computed": s.get(k, z)["macs_computed"], "bound": s.get(k, z)["bound"]} for k in keys}

    by_type = merge(dt, st, TABLE1_TYPES)
    by_block = merge(db, sb, ("block1", "block2", "block3", "up1", "up2", "up3"))
    total = {f: sum(v[f] for v in by_type.values()) for f in ("dense", "sparse", "sparse_computed", "bound")}
    conv = {f: sum(v[f] / _kernel_of(k) ** 2 for k, v in by_type.items()) for f in ("dense", "sparse", "bound")}
    return {
        "pillars": n0,
        "density": n0 / (ny * nx),
        "active_sites": {lc.block: lc.out_sites for lc in sparse_layers if lc.kind == "sparse_down"},
        "by_type": by_type,
        "by_block": by_block,
        "total": total,
        "convolutions": conv,
        "head": {"dense": head_macs(cfg, None), "sparse": head_macs(cfg, active_block1 if sparse_head else None)},
    }


def count_frames(
    cfg: ExperimentConfig, points_list: Sequence[np.ndarray], frame_ids: Sequence[str] | None = None, *,
    progress: bool = False,
) -> dict:
    """Op counts of every frame (points (N, C) float32, sensor frame, already range-filtered) and their summary
    (``progress``: a bar on stderr when it is a terminal).

    The sparse counts come from ``cfg.model`` if it is a sparse variant, else from the same config with
    ``backbone: sparse``; the dense counts from the same config with ``backbone: dense``.
    """
    dense_cfg, sparse_cfg = variants(cfg.model)
    dense_layers = dense_counts(dense_cfg)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        model = build_model(sparse_cfg).eval()
    frames = []
    ids = list(frame_ids) if frame_ids is not None else [str(i) for i in range(len(points_list))]
    bar = tqdm(total=len(ids), desc="counting ops", unit="frame", disable=None if progress else True, leave=False)
    for fid, pts in zip(ids, points_list):
        voxels = model.voxelize([torch.from_numpy(np.ascontiguousarray(pts, dtype=np.float32))])
        coords = voxels.coords
        layers = sparse_counts(model, coords, sparse_cfg)
        block1 = next((lc.out_sites for lc in layers if lc.kind == "sparse_down"), int(coords.shape[0]))
        fc = frame_counts(dense_layers, layers, int(coords.shape[0]), sparse_cfg, block1,
                          sparse_cfg.head == "sparse_exact")
        fc["frame_id"] = fid
        fc["layers"] = [asdict(lc) for lc in layers]
        frames.append(fc)
        bar.update(1)
    bar.close()
    return {
        "config": {"dense": dense_cfg.backbone, "sparse": sparse_cfg.backbone,
                   "output_shape": list(sparse_cfg.output_shape), "pfn_channels": sparse_cfg.pfn_channels,
                   "layer_channels": list(sparse_cfg.layer_channels), "layer_nums": list(sparse_cfg.layer_nums)},
        "dense_layers": [asdict(lc) for lc in dense_layers],
        "frames": frames,
        "summary": summarize(frames, sparse_cfg),
    }


def _is_paper_architecture(cfg: ModelConfig) -> bool:
    c = cfg.pfn_channels
    return (tuple(cfg.layer_channels) == (c, 2 * c, 4 * c) and tuple(cfg.layer_nums) == (3, 5, 5)
            and tuple(cfg.neck_channels) == (2 * c,) * 3 and tuple(cfg.upsample_strides) == (1, 2, 4)
            and cfg.backbone == "sparse")


def summarize(frames: Sequence[dict], cfg: ModelConfig) -> dict:
    """Across frames: density, sparse/dense and sparse/bound ratios (median, min, max), and Table I at the median D."""
    d = np.array([f["density"] for f in frames])
    tot = {k: np.array([f["total"][k] for f in frames], dtype=np.float64)
           for k in ("dense", "sparse", "sparse_computed", "bound")}

    def stats(v: np.ndarray) -> dict[str, float]:
        return {"median": float(np.median(v)), "min": float(v.min()), "max": float(v.max())}

    out = {
        "frames": len(frames),
        "density": stats(d),
        "sparse_over_dense": stats(tot["sparse"] / tot["dense"]),
        "sparse_over_bound": stats(tot["sparse"] / tot["bound"]),
        "bound_over_dense": stats(tot["bound"] / tot["dense"]),
        "computed_over_bound": stats(tot["sparse_computed"] / tot["bound"]),
        "max_type_sparse_over_bound": float(max(v["sparse"] / v["bound"] for f in frames for v in f["by_type"].values()
                                                if v["bound"] > 0)),
        "mean_macs_per_frame": {k: float(v.mean()) for k, v in tot.items()},
        "mean_by_type": {t: {k: float(np.mean([f["by_type"][t][k] for f in frames]))
                             for k in ("dense", "sparse", "sparse_computed", "bound")}
                         for t in frames[0]["by_type"]},
        "paper_architecture": _is_paper_architecture(cfg),
    }
    if out["paper_architecture"]:
        ny, nx = cfg.output_shape
        t1 = table1(float(np.median(d)), cfg.pfn_channels, ny, nx)
        out["table1_at_median_density"] = t1
        dense_conv = sum(v["dense"] for v in t1.values())
        bound_conv = sum(v["bound"] for v in t1.values())
        out["table1_fewer_convolutions_at_least"] = 1.0 - bound_conv / dense_conv
    return out


def count_dataset(
    config_path: str | Path, data_dir: str | Path, split: str = "test", frames: int | None = 20, start: int = 0, *,
    progress: bool = False,
) -> dict:
    """``detector ops``: load the config and ``frames`` frames of ``split``, count every frame (``progress``: bars on
    stderr when it is a terminal)."""
    from detector.data.experiment import load_eval_frames

    cfg = load_experiment(config_path)
    data = load_eval_frames(cfg, data_dir, split, frames, start, progress=progress)
    result = count_frames(cfg, [f.points for f in data], [f.frame_id for f in data], progress=progress)
    result["config"]["path"] = str(config_path)
    result["data"] = {"root": str(data_dir), "split": split}
    return result


def _g(x: float) -> str:
    """MACs in G / M with three significant digits."""
    if x >= 1e9:
        return f"{x / 1e9:.3g} G"
    if x >= 1e6:
        return f"{x / 1e6:.3g} M"
    return f"{x:,.0f}"


def format_counts(result: dict, markdown: bool = False) -> str:
    """Mean-per-frame MACs per conv type, then per frame: D, totals and ratios; then the summary lines."""
    s = result["summary"]
    header = ["conv type", "dense", "sparse exact", "Table I bound", "exact / bound", "sparse computed"]
    rows = []
    for t, v in s["mean_by_type"].items():
        ratio = f"{v['sparse'] / v['bound']:.3f}" if v["bound"] else "-"
        rows.append([t, _g(v["dense"]), _g(v["sparse"]), _g(v["bound"]), ratio, _g(v["sparse_computed"])])
    m = s["mean_macs_per_frame"]
    rows.append(["total", _g(m["dense"]), _g(m["sparse"]), _g(m["bound"]), f"{m['sparse'] / m['bound']:.3f}",
                 _g(m["sparse_computed"])])
    frame_header = ["frame", "D", "pillars", "dense", "sparse exact", "bound", "exact/bound", "exact/dense"]
    frame_rows = [[f["frame_id"], f"{f['density']:.5f}", str(f["pillars"]), _g(f["total"]["dense"]),
                   _g(f["total"]["sparse"]), _g(f["total"]["bound"]),
                   f"{f['total']['sparse'] / f['total']['bound']:.3f}",
                   f"{f['total']['sparse'] / f['total']['dense']:.4f}"] for f in result["frames"]]

    def table(h: list[str], rs: list[list[str]]) -> list[str]:
        if markdown:
            return ["| " + " | ".join(h) + " |", "|" + "---|" * len(h)] + ["| " + " | ".join(r) + " |" for r in rs]
        widths = [max(len(r[i]) for r in [h, *rs]) for i in range(len(h))]
        fmt = "  ".join(f"{{:<{w}}}" if i == 0 else f"{{:>{w}}}" for i, w in enumerate(widths))
        return [fmt.format(*h)] + [fmt.format(*r) for r in rs]

    cfg = result["config"]
    lines = [f"MACs per frame (mean over {s['frames']} frames), backbone + neck, {cfg['output_shape'][0]}x"
             f"{cfg['output_shape'][1]} pseudo-image; dense = {cfg['dense']}, sparse = {cfg['sparse']}", ""]
    lines += table(header, rows) + [""] + table(frame_header, frame_rows) + [""]
    pre = "- " if markdown else ""
    lines.append(f"{pre}density D: median {s['density']['median']:.5f} (min {s['density']['min']:.5f}, max "
                 f"{s['density']['max']:.5f})")
    lines.append(f"{pre}exact sparse / dense MACs: median {s['sparse_over_dense']['median']:.4f} "
                 f"(min {s['sparse_over_dense']['min']:.4f}, max {s['sparse_over_dense']['max']:.4f})")
    lines.append(f"{pre}exact sparse / Table I bound: median {s['sparse_over_bound']['median']:.3f}, max "
                 f"{s['sparse_over_bound']['max']:.3f}; worst single conv type {s['max_type_sparse_over_bound']:.3f} "
                 "(<= 1 always)")
    lines.append(f"{pre}as computed by detector.sparse (zero taps included) / bound: median "
                 f"{s['computed_over_bound']['median']:.3f}, max {s['computed_over_bound']['max']:.3f}")
    if "table1_fewer_convolutions_at_least" in s:
        lines.append(f"{pre}Table I at the median D: sparse performs at least "
                     f"{100 * s['table1_fewer_convolutions_at_least']:.1f}% fewer convolutions than dense "
                     f"(paper: >= {MATTERPORT_CHAIR_FEWER_CONVOLUTIONS:.0%} at Matterport-Chair's D = "
                     f"{MATTERPORT_CHAIR_DENSITY.median:.5f}, >= {KITTI_FEWER_CONVOLUTIONS:.0%} at KITTI's "
                     f"{KITTI_DENSITY.median:.5f})")
    head = result["frames"][0]["head"]
    lines.append(f"{pre}head (1x1 convs, not in Table I): dense {_g(head['dense'])} MACs/frame"
                 + (f"; exact sparse head {_g(head['sparse'])} (frame {result['frames'][0]['frame_id']})"
                    if head["sparse"] != head["dense"] else ""))
    lines.append(f"{pre}units: MACs; the paper's 'convolutions' are MACs / k^2")
    return "\n".join(lines)
