"""The dense / sparse backbone runtime ratio against pseudo-image density D, with the op-count ratio beside it.

The paper's speed-up rests on low density (Matterport-Chair's median D against KITTI's, ``mpchair.paper``); the curve
lets a reader place any sensor on it. Per density D of :data:`DENSITIES`, ``frames`` pseudo-images of clustered sites
(:func:`detector.sparse.synthetic.clustered_sites`: blobs and wall segments with about 4 active 8-neighbours per site,
like real scans; ``round(D * H * W)`` sites on the model's canvas, one seed per frame) with random non-negative pillar
features (a ReLU's range). Each frame goes through both models' Backbone (``backbone_neck``, the paper's Backbone timer:
backbone + neck, the sparse model's todense included; the scatter / SparseTensor wrap before it is untimed), the two
models interleaved per frame with the order alternating, ``trials`` times. Weights are random (seeded): the backbone's
runtime does not depend on them.

Beside it, the op-count ratio of the same sites (:mod:`detector.opcount`): the dense backbone + neck's MACs over the
sparse one's exact (rulebook) MACs. The runtime ratio is the ratio of the per-frame medians. Two densities are read off
the curve (:func:`crossings`): where the runtime ratio falls to 1 (sparse no longer faster), and where it meets the
op-count ratio (the sparse ops as efficient per MAC as the dense ones); either may lie outside the range measured.
Optionally real frames (``real``: points (N, C), sensor frame) are timed the same way at their own D, as a check of
the synthetic curve. Times in ms.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from detector.checkpoint import load_model
from detector.config import ModelConfig, load_experiment
from detector.device import machine_info, synchronize, use_device
from detector.models import PointPillars
from detector.opcount import dense_counts, sparse_counts
from detector.sparse.synthetic import clustered_sites
from mpchair.core.errors import InputError
from mpchair.paper import KITTI_DENSITY, MATTERPORT_CHAIR_DENSITY

#: Densities of the curve: from below Matterport-Chair's to KITTI's median (the paper's two medians, KITTI's rounded).
DENSITIES: tuple[float, ...] = (0.002, 0.003, 0.005, 0.0075, 0.01, 0.015, 0.02, 0.0246)
#: The paper's median densities (pillars / canvas), marked on the plot.
PAPER_DENSITY = {"Matterport-Chair (paper)": MATTERPORT_CHAIR_DENSITY.median, "KITTI": KITTI_DENSITY.median}


@torch.no_grad()
def time_backbone(model: PointPillars, features: torch.Tensor, coords: torch.Tensor, device: torch.device) -> float:
    """Milliseconds of ``model.backbone_neck`` on one pseudo-image: ``features`` (P, C) at ``coords`` (P, 3)
    ``[0, iy, ix]``; the Feature Net (scatter or SparseTensor wrap) runs untimed before it."""
    x = model.feature_net(features, coords, 1)
    synchronize(device)
    t0 = time.perf_counter()
    model.backbone_neck(x)
    synchronize(device)
    return (time.perf_counter() - t0) * 1e3


def site_frames(shape: tuple[int, int], density: float, frames: int, channels: int,
                seed: int) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """``frames`` (features (P, channels) float32 in [0, 1), coords (P, 3) int64) of clustered sites at ``density`` on
    a ``shape`` (ny, nx) canvas; frame k uses seed ``seed + k`` for its sites and its features."""
    out = []
    for k in range(frames):
        coords = clustered_sites(shape, density, 1, seed + k)
        gen = torch.Generator().manual_seed(seed + k)
        out.append((torch.rand(coords.shape[0], channels, generator=gen), coords))
    return out


def _log_interp(x0: float, x1: float, y0: float, y1: float) -> float:
    """Where the line through (log x0, y0), (log x1, y1) crosses y = 0."""
    t = y0 / (y0 - y1)
    return math.exp(math.log(x0) + t * (math.log(x1) - math.log(x0)))


def crossings(densities: Sequence[float], runtime: Sequence[float], ops: Sequence[float]) -> dict:
    """Two densities read off the curve, interpolated linearly in log D and log ratio between the points around them:
    ``ratio_one`` where the runtime ratio falls to 1, ``meets_ops`` where it meets the op-count ratio (None: not in
    the range measured). ``ratio_one_extrapolated``: without a crossing, where the log-log line through the last two
    points reaches 1 (None when it does not fall), marked as extrapolated."""
    logs = [math.log(r) for r in runtime]
    gaps = [math.log(r) - math.log(o) for r, o in zip(runtime, ops)]

    def first_crossing(values: Sequence[float]) -> float | None:
        if values[0] <= 0:
            return densities[0]
        for i in range(1, len(values)):
            if values[i] <= 0:
                return _log_interp(densities[i - 1], densities[i], values[i - 1], values[i])
        return None

    out = {"ratio_one": first_crossing(logs), "meets_ops": None, "ratio_one_extrapolated": None}
    if gaps[0] >= 0:
        out["meets_ops"] = densities[0]
    else:
        for i in range(1, len(gaps)):
            if gaps[i] >= 0:
                out["meets_ops"] = _log_interp(densities[i - 1], densities[i], gaps[i - 1], gaps[i])
                break
    if out["ratio_one"] is None and len(logs) >= 2 and logs[-1] < logs[-2]:
        out["ratio_one_extrapolated"] = _log_interp(densities[-2], densities[-1], logs[-2], logs[-1])
    return out


def _macs_ratio(sparse_net: PointPillars, cfg: ModelConfig, coords: torch.Tensor,
                dense_macs: int) -> tuple[float, float]:
    """(dense MACs / sparse exact MACs, dense MACs / MACs the sparse code computes) of one frame's sites ``coords``,
    for the sparse model ``sparse_net`` built from ``cfg``."""
    layers = sparse_counts(sparse_net, coords, cfg)
    exact = sum(lc.macs for lc in layers)
    computed = sum(lc.macs_computed for lc in layers)
    return dense_macs / max(exact, 1), dense_macs / max(computed, 1)


def density_curve(dense_config: str | Path, sparse_config: str | Path, *, densities: Sequence[float] = DENSITIES,
                  frames: int = 3, trials: int = 3, warmup: int = 2, threads: int | None = None, seed: int = 0,
                  real: Sequence[tuple[str, np.ndarray]] = ()) -> dict:
    """The curve of the module docstring: ``{"points": [{"density", "pillars", "dense_ms", "sparse_ms",
    "runtime_ratio", "op_ratio", "computed_op_ratio"}], "real": [...same, plus "frame_id"], "crossings",
    "geometry", "machine", "protocol"}``. CPU; both configs must share the canvas."""
    if frames < 1 or trials < 1 or warmup < 0 or not densities:
        raise InputError(f"need densities, frames >= 1, trials >= 1, warmup >= 0 (got {len(densities)}, {frames}, "
                         f"{trials}, {warmup})")
    if any(not 0 < d < 1 for d in densities):
        raise InputError(f"densities must lie in (0, 1), got {list(densities)}")
    dev = use_device("cpu", threads)
    cfgs = [load_experiment(c) for c in (dense_config, sparse_config)]
    if cfgs[0].model.backbone != "dense" or cfgs[1].model.backbone == "dense":
        raise InputError("the density curve needs a dense config first and a sparse one second", dense_config)
    if cfgs[0].model.output_shape != cfgs[1].model.output_shape:
        raise InputError(f"the two configs' canvases differ: {cfgs[0].model.output_shape} vs "
                         f"{cfgs[1].model.output_shape}", sparse_config)
    dense, sparse = (load_model(c, None, dev, seed=seed) for c in cfgs)
    shape = tuple(cfgs[0].model.output_shape)
    channels = cfgs[0].model.pfn_channels
    dense_macs = sum(lc.macs for lc in dense_counts(cfgs[0].model))

    def measure(items: list[tuple[torch.Tensor, torch.Tensor]]) -> tuple[list[float], list[float]]:
        d_ms, s_ms = [], []
        for t in range(trials):
            for i, (feats, coords) in enumerate(items):
                pair = {}
                for name in (("dense", "sparse") if (t * len(items) + i) % 2 == 0 else ("sparse", "dense")):
                    pair[name] = time_backbone(dense if name == "dense" else sparse, feats, coords, dev)
                d_ms.append(pair["dense"])
                s_ms.append(pair["sparse"])
        return d_ms, s_ms

    def point(items: list[tuple[torch.Tensor, torch.Tensor]]) -> dict:
        d_ms, s_ms = measure(items)
        ratios = [_macs_ratio(sparse, cfgs[1].model, coords, dense_macs) for _, coords in items]
        pillars = [int(c.shape[0]) for _, c in items]
        return {"density": float(np.mean(pillars)) / (shape[0] * shape[1]), "pillars": float(np.mean(pillars)),
                "dense_ms": float(np.median(d_ms)), "sparse_ms": float(np.median(s_ms)),
                "runtime_ratio": float(np.median(d_ms) / max(np.median(s_ms), 1e-9)),
                "op_ratio": float(np.median([r[0] for r in ratios])),
                "computed_op_ratio": float(np.median([r[1] for r in ratios]))}

    warm = site_frames(shape, densities[len(densities) // 2], 1, channels, seed + 10_000)
    for _ in range(warmup):
        measure(warm)
    points = []
    for j, d in enumerate(densities):
        p = point(site_frames(shape, d, frames, channels, seed + 1000 * j))
        points.append({**p, "target_density": float(d)})
    real_points = []
    with torch.no_grad():
        for fid, pts in real:
            voxels = dense.voxelize([torch.from_numpy(np.ascontiguousarray(pts, dtype=np.float32))])
            feats, coords = dense.pillar_net(voxels)
            real_points.append({**point([(feats, coords)]), "frame_id": fid})
    m = cfgs[0].model
    return {
        "sites": "clustered (detector.sparse.synthetic.clustered_sites), random features in [0, 1)",
        "points": points,
        "real": real_points,
        "crossings": crossings([p["density"] for p in points], [p["runtime_ratio"] for p in points],
                               [p["op_ratio"] for p in points]),
        "geometry": {"output_shape": list(m.output_shape), "voxel_size": list(m.voxel_size),
                     "point_cloud_range": list(m.point_cloud_range)},
        "configs": {"dense": str(dense_config), "sparse": str(sparse_config)},
        "machine": machine_info(dev),
        "protocol": {"frames_per_density": frames, "trials": trials, "warmup": warmup, "seed": seed,
                     "weights": f"random (seed {seed}; timing only)", "timed": "backbone_neck",
                     "interleaved": True, "runtime_ratio": "median dense ms / median sparse ms over frames x trials",
                     "op_ratio": "dense MACs / sparse exact MACs (detector.opcount), median over frames"},
    }


def format_curve(result: dict) -> str:
    """The curve as a Markdown table (one row per density, then the real frames) and the two crossings."""
    lines = ["| D | pillars | dense backbone (ms) | sparse backbone (ms) | runtime ratio dense / sparse | "
             "op-count ratio dense / sparse (exact) | runtime / op ratio |", "|---|---|---|---|---|---|---|"]
    for p in result["points"]:
        lines.append(f"| {p['density']:.4f} | {p['pillars']:,.0f} | {p['dense_ms']:.1f} | {p['sparse_ms']:.1f} | "
                     f"{p['runtime_ratio']:.2f}x | {p['op_ratio']:.1f}x | {p['runtime_ratio'] / p['op_ratio']:.3f} |")
    for p in result["real"]:
        lines.append(f"| {p['density']:.4f} (real frame {p['frame_id']}) | {p['pillars']:,.0f} | {p['dense_ms']:.1f} | "
                     f"{p['sparse_ms']:.1f} | {p['runtime_ratio']:.2f}x | {p['op_ratio']:.1f}x | "
                     f"{p['runtime_ratio'] / p['op_ratio']:.3f} |")
    return "\n".join(lines + ["", crossings_text(result)])


def crossings_text(result: dict) -> str:
    """One sentence per crossing of :func:`crossings`, in words."""
    c, pts = result["crossings"], result["points"]
    lo, hi = pts[0]["density"], pts[-1]["density"]
    if c["ratio_one"] is not None and pts[0]["runtime_ratio"] <= 1:
        one = f"the runtime ratio is at or below 1 already at D = {lo:.4f} ({pts[0]['runtime_ratio']:.2f}x)"
    elif c["ratio_one"] is not None:
        one = f"the runtime ratio falls to 1 at D = {c['ratio_one']:.4f}"
    else:
        one = (f"the runtime ratio stays above 1 up to D = {hi:.4f} ({pts[-1]['runtime_ratio']:.2f}x there)"
               + (f"; the log-log line through the last two points reaches 1 at D = "
                  f"{c['ratio_one_extrapolated']:.3f} (extrapolated)" if c["ratio_one_extrapolated"] else ""))
    if c["meets_ops"] is not None and pts[0]["runtime_ratio"] >= pts[0]["op_ratio"]:
        meet = f"it is at or above the op-count ratio already at D = {lo:.4f}"
    elif c["meets_ops"] is not None:
        meet = f"it meets the op-count ratio at D = {c['meets_ops']:.4f}"
    else:
        eff = [p["runtime_ratio"] / p["op_ratio"] for p in pts]
        meet = (f"it stays below the op-count ratio from D = {lo:.4f} to {hi:.4f} (at {min(eff):.0%} to "
                f"{max(eff):.0%} of it: a sparse MAC takes {1 / max(eff):.1f}-{1 / min(eff):.1f}x the time of a "
                "dense one here)")
    return f"Crossings: {one}; {meet}."


def plot_curve(result: dict, path: Path, marks: dict[str, float] | None = None) -> Path:
    """PNG of :func:`curve_figure`, written atomically."""
    import matplotlib.pyplot as plt

    from mpchair.core.atomic import atomic_open

    fig = curve_figure(result, marks)
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png")
    plt.close(fig)
    return path


def curve_figure(result: dict, marks: dict[str, float] | None = None):
    """Both ratios against D (log axes), the real frames as crosses, vertical lines at the paper's densities and
    ``marks`` ({label: D}, e.g. this dataset's median), each named in the legend beside the plot."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = result["points"]
    d = [p["density"] for p in pts]
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullFormatter

    fig, ax = plt.subplots(figsize=(8.0, 4.0), dpi=110)
    ax.plot(d, [p["runtime_ratio"] for p in pts], "-o", color="tab:blue", label="runtime ratio (backbone)")
    ax.plot(d, [p["op_ratio"] for p in pts], "--s", color="tab:orange", label="op-count ratio (exact MACs)")
    if result["real"]:
        ax.plot([p["density"] for p in result["real"]], [p["runtime_ratio"] for p in result["real"]], "x",
                color="tab:green", label="runtime ratio, real frames")
    ax.axhline(1.0, color="grey", lw=0.8)
    # the reference densities in the legend, not as text at their lines: close densities (the paper's Matterport-Chair
    # 0.0075, this dataset's 0.0079) put their labels on top of each other and of the markers
    for (label, x), color in zip({**PAPER_DENSITY, **(marks or {})}.items(), ("k", "tab:red", "tab:purple", "c")):
        ax.axvline(x, color=color, ls=":", lw=1.2, label=f"D = {x:.4f}: {label}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    # plain decimals at a few densities: the log axis's 2x10^-3, 3x10^-3, 4x10^-3 minor labels collided
    lo, hi = ax.get_xlim()
    ticks = [t for t in (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1) if lo <= t <= hi]
    ax.xaxis.set_major_locator(FixedLocator(ticks))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("pseudo-image density D (non-empty pillars / canvas)")
    ax.set_ylabel("dense / sparse")
    shape = result["geometry"]["output_shape"]
    ax.set_title(f"dense / sparse backbone, {shape[0]} x {shape[1]} canvas, random weights", fontsize=9)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    fig.tight_layout()
    return fig
