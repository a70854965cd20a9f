"""Per-component runtime of dense and sparse PointPillars: the paper's Tables II / IV protocol, made measurable.

Components (one :class:`detector.models.PointPillars` stage each, batch 1, eval mode, ``torch.no_grad``):

| key | paper column | what runs |
|---|---|---|
| ``to_device`` | To Device | ``torch.from_numpy(points).to(device)`` (on CPU: the tensor wrap only, no copy) |
| ``feature_extract`` | Feature Extract | ``voxelize`` + ``pillar_net`` |
| ``feature_net`` | Feature Net | ``feature_net``: scatter to the dense canvas, or wrapping as a ``SparseTensor`` |
| ``backbone`` | Backbone | ``backbone_neck``: backbone + neck, incl. the sparse model's todense + concat |
| ``head`` | Head | ``head`` (three 1x1 convs, or the exact sparse head) |
| ``bbox_extract`` | BBox Extract | ``postprocess``: top-k, decode, rotated NMS, direction fix |
| ``total`` | Total time | the sum of the six, i.e. first stamp to last stamp of a frame |

Protocol: every model is warmed up on the first frames, then ``trials`` passes over the same ``frames`` frames are
timed. Within a pass the models are **interleaved per frame** (the order alternates from frame to frame), so load
spikes of a shared machine hit all models alike. A trial's value of a component is its mean over the frames (the
per-instance runtime); the reported mean ± std is over trials (population std), as the paper's tables. On CUDA the
device is synchronised before every stamp; stamps are ``time.perf_counter``.

Back to back: a component runs at the speed of the state the stage before it left (caches, predictors, allocator). The
paper calls the Head and BBox Extract identical in both models, yet in the per-frame pipeline each one follows a
model-specific backbone: on a 2-core AMX Xeon the same post-processing took 1.6x as long after the dense backbone
(400 ms of oneDNN convolutions) as after the sparse one on identical work (random weights; 1.25-2.5x on trained ones),
even a single ``amax`` over the class map did, and the gap vanished when a tiny dummy call warmed the code path first
(the paper saw the same effect on GPUs and put it down to pipelining). So after the timed passes, ``trials`` more passes
time these :data:`SHARED` components **back to back**: per frame every model runs to its neck (untimed), then every
model's Head, then every model's BBox Extract, each on its own maps, in an order rotated from frame to frame, so each
model's component follows the same kind of stage as the others'. The per-frame columns stay the paper's protocol (what a
pipeline pays); the back-to-back columns are the components' own cost, the one to compare between models.

The result records the data's pseudo-image density ``D`` (pillars indexed by :func:`mpchair.geometry.pillar_coords`,
over the model's ``output_shape`` canvas) and the machine: CPU model, threads, torch version, GPU, load average, the
glibc allocator settings ``MALLOC_MMAP_MAX_`` / ``MALLOC_TRIM_THRESHOLD_`` (they can dominate CPU timings, see
``docs/benchmarks.md``) and page faults per frame of each model (``resource.getrusage``, whole process).
"""

from __future__ import annotations

import math
import os
import platform
import resource
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from detector.checkpoint import load_model
from detector.config import pseudoimage_geometry
from detector.data.experiment import load_eval_frames
from detector.device import use_device
from detector.models import ExperimentConfig, PointPillars, load_experiment
from mpchair.core.errors import InputError
from mpchair.geometry import frame_density

#: Peers ``run_bench(peer=...)`` knows, and the peer row's name (detector.peer imports Open3D-ML only when used).
PEERS: tuple[str, ...] = ("open3d-ml",)
PEER_NAME = "open3d-ml"

#: Component keys in table order (``total`` last).
COMPONENTS: tuple[str, ...] = ("to_device", "feature_extract", "feature_net", "backbone", "head", "bbox_extract",
                               "total")
#: Components the paper calls identical in every model that follow a model-specific stage: also timed back to back.
SHARED: tuple[str, ...] = ("head", "bbox_extract")
#: Column titles of the paper's runtime tables.
TITLES: dict[str, str] = {
    "to_device": "To Device",
    "feature_extract": "Feature Extract",
    "feature_net": "Feature Net",
    "backbone": "Backbone",
    "head": "Head",
    "bbox_extract": "BBox Extract",
    "total": "Total",
}
MALLOC_ENV: tuple[str, ...] = ("MALLOC_MMAP_MAX_", "MALLOC_TRIM_THRESHOLD_")
#: The allocator setting under which freed memory is reused instead of returned to the OS after every frame.
MALLOC_REUSE: dict[str, str] = {"MALLOC_MMAP_MAX_": "0", "MALLOC_TRIM_THRESHOLD_": "68719476736"}


# --- data ---------------------------------------------------------------------------------------------------------
def density_summary(values: Sequence[float]) -> dict[str, float]:
    """``{"frames", "median", "mean", "min", "max"}`` of per-frame densities."""
    v = np.asarray(values, dtype=np.float64)
    return {"frames": int(v.size), "median": float(np.median(v)), "mean": float(v.mean()), "min": float(v.min()),
            "max": float(v.max())}


# --- models -------------------------------------------------------------------------------------------------------
def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _faults() -> int:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return int(r.ru_minflt + r.ru_majflt)


@torch.no_grad()
def time_frame(model: PointPillars, points: np.ndarray, device: torch.device) -> tuple[dict[str, float], int]:
    """Run one frame through the five stages with a stamp after each: ``({component: ms}, detections)``."""
    stamps = []
    _sync(device)
    stamps.append(time.perf_counter())
    pts = torch.from_numpy(points).to(device)
    _sync(device)
    stamps.append(time.perf_counter())
    voxels = model.voxelize([pts])
    features, coords = model.pillar_net(voxels)
    _sync(device)
    stamps.append(time.perf_counter())
    x = model.feature_net(features, coords, voxels.batch_size)
    _sync(device)
    stamps.append(time.perf_counter())
    x, active = model.backbone_neck(x)
    _sync(device)
    stamps.append(time.perf_counter())
    out = model.head(x, active)
    _sync(device)
    stamps.append(time.perf_counter())
    dets = model.postprocess(out.cls, out.reg, out.dir)
    _sync(device)
    stamps.append(time.perf_counter())
    ms = {k: (stamps[i + 1] - stamps[i]) * 1e3 for i, k in enumerate(COMPONENTS[:-1])}
    ms["total"] = (stamps[-1] - stamps[0]) * 1e3
    return ms, int(sum(int(d.boxes.shape[0]) for d in dets))


@torch.no_grad()
def time_shared(models: Sequence[PointPillars], points: Sequence[np.ndarray], device: torch.device,
                first: int) -> np.ndarray:
    """One frame through every model to its neck (untimed), then every model's Head, then every model's BBox Extract,
    starting with model ``first`` (then ``first + 1``, ... cyclically): ``(len(models), len(SHARED))`` ms."""
    necks = []
    for model, pts in zip(models, points):
        voxels = model.voxelize([torch.from_numpy(pts).to(device)])
        features, coords = model.pillar_net(voxels)
        necks.append(model.backbone_neck(model.feature_net(features, coords, voxels.batch_size)))
    k = len(models)
    order = [(first + j) % k for j in range(k)]
    ms = np.zeros((k, len(SHARED)))
    outs: dict[int, object] = {}
    for j in order:
        _sync(device)
        t0 = time.perf_counter()
        outs[j] = models[j].head(*necks[j])
        _sync(device)
        ms[j, 0] = (time.perf_counter() - t0) * 1e3
    for j in order:
        out = outs[j]
        _sync(device)
        t0 = time.perf_counter()
        models[j].postprocess(out.cls, out.reg, out.dir)
        _sync(device)
        ms[j, 1] = (time.perf_counter() - t0) * 1e3
    return ms


# --- machine ------------------------------------------------------------------------------------------------------
def cpu_model() -> str:
    """The CPU's marketing name (``/proc/cpuinfo``), or ``platform.processor()``."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info(device: torch.device) -> dict:
    """What the timings depend on: CPU, threads, torch, GPU, load, allocator env."""
    info = {
        "cpu": cpu_model(),
        "logical_cpus": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "python": platform.python_version(),
        "device": str(device),
        "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
        "loadavg_1m": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "malloc_env": {k: os.environ.get(k) for k in MALLOC_ENV},
    }
    info["allocator"] = (
        "reuse" if all(os.environ.get(k) == v for k, v in MALLOC_REUSE.items())
        else "default" if not any(os.environ.get(k) for k in MALLOC_ENV) else "custom"
    )
    return info


# --- the benchmark ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BenchModel:
    """One model to time: display ``name``, its ``config`` path and optional ``checkpoint``."""

    name: str
    config: str
    checkpoint: str | None = None


def default_name(cfg: ExperimentConfig, path: str | Path) -> str:
    """``dense`` / ``sparse`` / ... from the backbone, plus ``+sparse_head`` for the exact sparse head."""
    name = cfg.model.backbone
    if cfg.model.head != "dense":
        name += "+sparse_head"
    return name


def run_bench(
    models: Sequence[BenchModel],
    data_dir: str | Path,
    *,
    split: str = "test",
    frames: int = 20,
    trials: int = 3,
    warmup: int = 3,
    device: str = "cpu",
    threads: int | None = None,
    seed: int = 0,
    peer: str | None = None,
    progress: bool = False,
) -> dict:
    """Time every model on the first ``frames`` frames of ``split``; returns the JSON-ready result. ``progress``:
    bars on stderr (loading, warm-up and timed frames) when it is a terminal.

    ``{"models": [{"name", "config", "weights", "components": {key: {"mean_ms", "std_ms"}}, "back_to_back": {shared
    key: {"mean_ms", "std_ms"}} (None for the peer and for a single model), "median_frame_ms",
    "min_frame_ms", "detections_per_frame", "page_faults_per_frame", "density_median", "peer"}], "density": {...},
    "machine": {...}, "protocol": {...}}``.

    ``peer="open3d-ml"`` adds Open3D-ML's own PointPillars as the last row (``"peer": "open3d-ml"``; ours have
    ``"peer": None``): built with the first model's architecture and grid and its weights (:mod:`detector.peer`; the
    first model must be dense), fed the first model's frames, interleaved per frame with the others. CPU only.
    """
    if not models:
        raise InputError("bench needs at least one --config")
    if frames < 1 or trials < 1 or warmup < 0:
        raise InputError(f"need frames >= 1, trials >= 1, warmup >= 0 (got {frames}, {trials}, {warmup})")
    dev = use_device(device, threads)
    cfgs = [load_experiment(m.config) for m in models]
    names = [m.name or default_name(c, m.config) for m, c in zip(models, cfgs)]
    if len(set(names)) != len(names):
        # two configs with the same backbone (e.g. a shape sweep): fall back to file stems
        names = [n if names.count(n) == 1 else f"{n}:{Path(m.config).stem}" for n, m in zip(names, models)]
    if peer is not None and peer not in PEERS:
        raise InputError(f"unknown peer {peer!r} (choose from {', '.join(PEERS)})")
    if peer is not None and device != "cpu":
        raise InputError(f"--peer {peer} times the CPU only (open3d-cpu); drop --device {device}")
    nets = [load_model(c, m.checkpoint, dev, seed=seed) for c, m in zip(cfgs, models)]
    data = [load_eval_frames(c, data_dir, split, frames, progress=progress) for c in cfgs]
    n = len(data[0])
    densities = [[frame_density(f.points, pseudoimage_geometry(c.model))[2] for f in d] for c, d in zip(cfgs, data)]
    # one timing function per row: ours, then the peer on the first model's frames
    runs = [lambda pts, net=net: time_frame(net, pts, dev) for net in nets]
    if peer is not None:
        from detector.peer import build_peer, time_peer_frame

        peer_net = build_peer(cfgs[0].model, nets[0])
        runs.append(lambda pts: time_peer_frame(peer_net, pts))
        data.append(data[0])
        densities.append(densities[0])

    # one bar step = one frame through every model; stderr, so a table or Markdown on stdout stays clean
    bar = tqdm(total=min(warmup, n) + trials * n * (2 if len(nets) > 1 else 1), desc="bench warm-up", unit="frame",
               disable=None if progress else True, leave=False)
    for i in range(min(warmup, n)):
        for run, d in zip(runs, data):
            run(d[i].points)
        bar.update(1)

    k = len(runs)
    # per model, trial, component: the mean over frames
    trial_means = np.zeros((k, trials, len(COMPONENTS)))
    per_frame = np.zeros((k, trials, n, len(COMPONENTS)))
    faults = np.zeros((k,), dtype=np.int64)
    dets = np.zeros((k,), dtype=np.int64)
    for t in range(trials):
        bar.set_description(f"bench trial {t + 1}/{trials}")
        for i in range(n):
            order = range(k) if (t * n + i) % 2 == 0 else reversed(range(k))  # alternate who goes first
            for j in order:
                f0 = _faults()
                ms, nd = runs[j](data[j][i].points)
                faults[j] += _faults() - f0
                dets[j] += nd
                per_frame[j, t, i] = [ms[c] for c in COMPONENTS]
            bar.update(1)
        trial_means[:, t] = per_frame[:, t].mean(axis=1)
    # the shared components back to back (ours only: the peer's stages are not ours to split)
    back = np.zeros((len(nets), trials, len(SHARED)))
    if len(nets) > 1:
        for t in range(trials):
            bar.set_description(f"bench back to back {t + 1}/{trials}")
            back[:, t] = np.mean([time_shared(nets, [d[i].points for d in data[: len(nets)]], dev,
                                              (t * n + i) % len(nets)) for i in range(n)], axis=0)
            bar.update(n)
    bar.close()

    weights = [str(m.checkpoint) if m.checkpoint else f"random (seed {seed}; untrained, timing only)" for m in models]
    rows = [(names[j], m, c, weights[j], None) for j, (m, c) in enumerate(zip(models, cfgs))]
    if peer is not None:
        rows.append((PEER_NAME, models[0], cfgs[0], f"{names[0]}'s weights, copied: {weights[0]}", peer))
    out_models = []
    for j, (name, m, c, w, p) in enumerate(rows):
        comps = {
            key: {"mean_ms": float(trial_means[j, :, ci].mean()), "std_ms": float(trial_means[j, :, ci].std())}
            for ci, key in enumerate(COMPONENTS)
        }
        out_models.append({
            "name": name,
            "peer": p,
            "config": str(m.config),
            "weights": w,
            "backbone": c.model.backbone,
            "head": c.model.head,
            "output_shape": list(c.model.output_shape),
            "components": comps,
            "back_to_back": None if p is not None or len(nets) < 2 else {
                key: {"mean_ms": float(back[j, :, si].mean()), "std_ms": float(back[j, :, si].std())}
                for si, key in enumerate(SHARED)
            },
            "median_frame_ms": {key: float(np.median(per_frame[j, :, :, ci])) for ci, key in enumerate(COMPONENTS)},
            "min_frame_ms": {key: float(per_frame[j, :, :, ci].min()) for ci, key in enumerate(COMPONENTS)},
            "detections_per_frame": float(dets[j]) / (trials * n),
            "page_faults_per_frame": float(faults[j]) / (trials * n),
            "density_median": float(np.median(densities[j])),
        })
    density = density_summary(densities[0])
    density["geometry"] = {"point_cloud_range": list(cfgs[0].model.point_cloud_range),
                           "voxel_size": list(cfgs[0].model.voxel_size),
                           "output_shape": list(cfgs[0].model.output_shape)}
    mach = machine_info(dev)
    if peer is not None:
        import open3d

        mach["open3d"] = open3d.__version__
    return {
        "models": out_models,
        "density": density,
        "machine": mach,
        "protocol": {"data": str(data_dir), "split": split, "frames": n, "frame_ids": [f.frame_id for f in data[0]],
                     "peer": peer, "trials": trials, "warmup": min(warmup, n), "batch_size": 1, "interleaved": True,
                     "back_to_back": list(SHARED) if len(nets) > 1 else [],
                     "std": "population std over trials of the per-trial mean over frames"},
    }


# --- formatting ---------------------------------------------------------------------------------------------------
def _fmt(x: float) -> str:
    return f"{x:,.3f}" if x < 100 else f"{x:,.1f}"


def ratio_rows(result: dict, section: str = "components") -> list[tuple[str, dict[str, float]]]:
    """Per-component speed-ups: ``first / other`` for every one of our models after the first (dense / sparse: > 1
    means sparse faster), then ``peer / ours`` for every one of our models (> 1 means ours is faster than the peer).
    ``section="back_to_back"``: the same for the :data:`SHARED` components timed back to back (ours only)."""
    ours = [m for m in result["models"] if not m.get("peer")]
    peers = [m for m in result["models"] if m.get("peer")]
    pairs = [(ours[0], m) for m in ours[1:]]
    if section == "components":
        pairs += [(p, m) for p in peers for m in ours]
    rows = []
    for a, b in pairs:
        if not a.get(section) or not b.get(section):
            continue
        r = {}
        for key in a[section]:
            ta, tb = a[section][key]["mean_ms"], b[section][key]["mean_ms"]
            r[key] = ta / tb if tb > 0 else math.inf
        rows.append((f"{a['name']} / {b['name']}", r))
    return rows


def machine_line(mach: dict) -> str:
    """One line describing the machine of a result."""
    line = (f"machine: {mach['cpu']}, {mach['torch_threads']} torch threads of {mach['logical_cpus']} CPUs, "
            f"torch {mach['torch']}, device {mach['device']}")
    if mach.get("gpu"):
        line += f" ({mach['gpu']})"
    if mach.get("loadavg_1m") is not None:
        line += f", load average {mach['loadavg_1m']:.2f} when it ended"
    return line


def format_table(result: dict, markdown: bool = False) -> str:
    """The paper-shaped table: one row per model (mean ± std ms), one ratio row per further model; then the shared
    components timed back to back (same shape), then notes."""
    lines = _table(result, "components", COMPONENTS, markdown)
    if any(m.get("back_to_back") for m in result["models"]):
        title = (f"{' and '.join(TITLES[k] for k in SHARED)} timed back to back (every model's, on its own maps, order "
                 "rotated per frame; the components' own cost, to compare between models):")
        lines += ["", title, ""] + _table(result, "back_to_back", SHARED, markdown)
    mach, dens, prot = result["machine"], result["density"], result["protocol"]
    env = ", ".join(f"{k}={v}" for k, v in mach["malloc_env"].items() if v is not None) or "unset"
    notes = [
        f"ms per frame, mean ± std over {prot['trials']} trials of {prot['frames']} frames ({prot['split']} split), "
        f"{prot['warmup']} warm-up frames, batch 1, models interleaved per frame",
        machine_line(mach),
        f"allocator: {mach['allocator']} ({env})",
        f"density D (pillars / {dens['geometry']['output_shape'][0]}x{dens['geometry']['output_shape'][1]}): median "
        f"{dens['median']:.5f}, min {dens['min']:.5f}, max {dens['max']:.5f} over {dens['frames']} frames",
    ]
    for m in result["models"]:
        what = (f"Open3D-ML {mach.get('open3d', '')}'s own PointPillars, the architecture and grid of "
                f"{result['models'][0]['name']} (detector/peer.py); " if m.get("peer") else "")
        notes.append(f"{m['name']}: {what}weights {m['weights']}; {m['page_faults_per_frame']:.0f} page faults/frame; "
                     f"{m['detections_per_frame']:.1f} detections/frame")
    prefix = "- " if markdown else ""
    return "\n".join(lines) + "\n\n" + "\n".join(prefix + n for n in notes)


def _table(result: dict, section: str, keys: Sequence[str], markdown: bool) -> list[str]:
    """Rows of one section (mean ± std ms per model that has it, then its ratio rows), as text or Markdown lines."""
    header = ["model", *(TITLES[k] for k in keys)]
    rows = [[m["name"], *(f"{_fmt(m[section][k]['mean_ms'])} ± {_fmt(m[section][k]['std_ms'])}" for k in keys)]
            for m in result["models"] if m.get(section)]
    rows += [[name, *(f"{r[k]:.2f}x" for k in keys)] for name, r in ratio_rows(result, section)]
    if markdown:
        cells = ["| " + " | ".join(r) + " |" for r in [header, *rows]]
        return [cells[0], "|" + "---|" * len(header), *cells[1:]]
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    fmt = "  ".join(f"{{:<{w}}}" if i == 0 else f"{{:>{w}}}" for i, w in enumerate(widths))
    return [fmt.format(*header)] + [fmt.format(*r) for r in rows]
