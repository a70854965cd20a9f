"""The total-time ratio with the reference's head layout: each model's per-frame stages as ``detector bench`` times
them, and the reference's three NCHW 1x1 convs (:func:`detector.models.reference_head.reference_head`) timed on the
same frame's neck map.

Per frame and model (the models interleaved, the order alternating from frame to frame, as ``detector bench``):

1. :func:`detector.bench.timing.time_frame`: the seven components with our fused head;
2. the frame again to its neck (untimed), an NCHW copy of the neck map (untimed: the reference's neck hands its head an
   NCHW map, ours a channels-last one, and that copy takes longer than the convs), then the reference's head, timed.

``total_reference_head`` is that frame's total with Head replaced by the reference head's time: the total is by
definition the sum of the stages (:func:`detector.bench.timing.stamps_to_ms`), so this is the pipeline a reference-
layout head would give, up to the state the different head leaves for BBox Extract. Times in ms per frame.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from detector.bench.run import BenchModel, display_names
from detector.bench.timing import COMPONENTS, time_frame
from detector.checkpoint import load_model
from detector.config import load_experiment
from detector.data.experiment import load_eval_frames
from detector.device import machine_info, synchronize, use_device
from detector.models import PointPillars
from detector.models.reference_head import nchw, reference_head
from mpchair.core.errors import InputError

#: The keys this bench adds to ``detector bench``'s components.
EXTRA = ("head_reference", "total_reference_head")


@torch.no_grad()
def time_reference_head(model: PointPillars, points: np.ndarray, device: torch.device) -> float:
    """Milliseconds of the reference's head on one frame (``points`` (N, C) float32, sensor frame): the stages up to
    the neck and the NCHW copy of its map run untimed."""
    voxels = model.voxelize([torch.from_numpy(points).to(device)])
    features, coords = model.pillar_net(voxels)
    x, _ = model.backbone_neck(model.feature_net(features, coords, voxels.batch_size))
    x = nchw(x)
    synchronize(device)
    t0 = time.perf_counter()
    reference_head(model.anchor_head, x)
    synchronize(device)
    return (time.perf_counter() - t0) * 1e3


def run_reference_head_bench(models: Sequence[BenchModel], data_dir: str | Path, *, split: str = "test",
                             frames: int = 20, trials: int = 3, warmup: int = 2, threads: int | None = None,
                             seed: int = 0) -> dict:
    """Every model's components (ours) and the reference head's, per the module docstring, on the first ``frames``
    frames of ``split``: ``{"models": [{"name", "config", "weights", "mean_ms": {component: ms}}], "ratios": {"total",
    "total_reference_head"} (first model / each other), "machine", "protocol"}``. CPU."""
    if not models:
        raise InputError("the reference-head bench needs at least one --config")
    if frames < 1 or trials < 1 or warmup < 0:
        raise InputError(f"need frames >= 1, trials >= 1, warmup >= 0 (got {frames}, {trials}, {warmup})")
    dev = use_device("cpu", threads)
    cfgs = [load_experiment(m.config) for m in models]
    names = display_names(models, cfgs)
    nets = [load_model(c, m.checkpoint, dev, seed=seed) for c, m in zip(cfgs, models)]
    data = [load_eval_frames(c, data_dir, split, frames) for c in cfgs]
    n = len(data[0])
    for i in range(min(warmup, n)):  # kernels, caches and the allocator settle
        for net, fs in zip(nets, data):
            time_frame(net, fs[i].points, dev)
            time_reference_head(net, fs[i].points, dev)
    keys = (*COMPONENTS, *EXTRA)
    per_frame = np.zeros((len(nets), trials, n, len(keys)))
    for t in range(trials):
        for i in range(n):
            order = range(len(nets)) if (t * n + i) % 2 == 0 else reversed(range(len(nets)))
            for j in order:
                ms, _ = time_frame(nets[j], data[j][i].points, dev)
                ref = time_reference_head(nets[j], data[j][i].points, dev)
                ms.update(head_reference=ref, total_reference_head=ms["total"] - ms["head"] + ref)
                per_frame[j, t, i] = [ms[k] for k in keys]
    means = per_frame.mean(axis=(1, 2))
    records = [{"name": name, "config": str(m.config),
                "weights": str(m.checkpoint) if m.checkpoint else f"random (seed {seed}; untrained, timing only)",
                "output_shape": list(c.model.output_shape), "mean_ms": dict(zip(keys, map(float, means[j])))}
               for j, (name, m, c) in enumerate(zip(names, models, cfgs))]
    first = records[0]["mean_ms"]
    ratios = {r["name"]: {k: first[k] / max(r["mean_ms"][k], 1e-9) for k in ("total", "total_reference_head")}
              for r in records[1:]}
    return {"models": records, "ratios": ratios, "machine": machine_info(dev),
            "protocol": {"data": str(data_dir), "split": split, "frames": n,
                         "frame_ids": [f.frame_id for f in data[0]], "trials": trials, "warmup": min(warmup, n),
                         "interleaved": True, "batch_size": 1,
                         "reference_head": "three 1x1 convs (class, box, direction) on an NCHW copy of the neck "
                                           "map, the copy untimed"}}


def format_reference_head(result: dict) -> str:
    """The result as a Markdown table: each model's Head (ours, the reference's) and Total (ours, with the reference's
    head) in ms per frame, then the first model / each other total-time ratios."""
    lines = ["| model | Head, ours (ms) | Head, reference layout (ms) | Total, ours (ms) | "
             "Total, reference head (ms) |", "|---|---|---|---|---|"]
    for r in result["models"]:
        ms = r["mean_ms"]
        lines.append(f"| {r['name']} | {ms['head']:.1f} | {ms['head_reference']:.1f} | {ms['total']:.1f} | "
                     f"{ms['total_reference_head']:.1f} |")
    first = result["models"][0]["name"]
    for name, ratio in result["ratios"].items():
        lines.append(f"| {first} / {name} | | | {ratio['total']:.2f}x | {ratio['total_reference_head']:.2f}x |")
    p, mach = result["protocol"], result["machine"]
    lines += ["", f"{p['frames']} frames of {p['split']} x {p['trials']} trials, interleaved per frame, batch 1; "
              f"{mach['cpu']}, {mach['torch_threads']} torch threads, allocator {mach['allocator']}."]
    return "\n".join(lines)
