"""Stamps around the paper's timing components: one frame through a model's stages, and the shared ones back to back.

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

On CUDA the device is synchronised before every stamp; stamps are ``time.perf_counter``, reported in ms.

Below the paper's components, :func:`time_calls` is the one timer of plain callables (a conv layer, a backbone, a
training step), interleaved, wall and CPU time and page faults: ``detector.bench.sparse_ratios`` and
``detector.bench.conv_forms`` time with it.
"""

from __future__ import annotations

import resource
import statistics
import time
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import torch

from detector.device import synchronize
from detector.models import PointPillars

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


def page_faults() -> int:
    """Page faults (minor + major) of this whole process so far (``resource.getrusage``)."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return int(r.ru_minflt + r.ru_majflt)


def time_call(fn: Callable[[], object]) -> tuple[float, float, int]:
    """Wall seconds, process CPU seconds (all threads, user + system) and page faults (:func:`page_faults`) of one
    call of ``fn``.

    On a shared machine the CPU time is the steadier measure of the work done; the wall time is what a dedicated
    machine would show only when the CPU is not oversubscribed.
    """
    f0 = page_faults()
    c0, t0 = time.process_time(), time.perf_counter()
    fn()
    dt, dc = time.perf_counter() - t0, time.process_time() - c0
    return dt, dc, page_faults() - f0


def time_calls(fns: Mapping[str, Callable[[], object]], repeats: int,
               warmup: int = 1) -> dict[str, dict[str, float]]:
    """``warmup`` untimed rounds, then ``repeats`` timed rounds of every function in turn (interleaved, so load
    spikes of a shared machine hit all alike): per name ``{"min_ms", "median_ms"}`` (wall), ``"cpu_min_ms"`` and
    ``"faults"`` (mean page faults per call). The caller sets eval mode / ``torch.no_grad`` as its rows need."""
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    samples: dict[str, list[tuple[float, float, int]]] = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            samples[k].append(time_call(fn))
    return {
        k: {
            "min_ms": 1e3 * min(t for t, _, _ in v),
            "median_ms": 1e3 * statistics.median(t for t, _, _ in v),
            "cpu_min_ms": 1e3 * min(c for _, c, _ in v),
            "faults": statistics.mean(f for _, _, f in v),
        }
        for k, v in samples.items()
    }


def stamps_to_ms(stamps: Sequence[float]) -> dict[str, float]:
    """``{component: ms}`` from the seven ``time.perf_counter`` stamps around the six stages (s), ``total`` the first
    to the last."""
    ms = {k: (stamps[i + 1] - stamps[i]) * 1e3 for i, k in enumerate(COMPONENTS[:-1])}
    ms["total"] = (stamps[-1] - stamps[0]) * 1e3
    return ms


@torch.no_grad()
def time_frame(model: PointPillars, points: np.ndarray, device: torch.device,
               faults: dict[str, int] | None = None) -> tuple[dict[str, float], int]:
    """Run one frame (``points`` (N, C) float32, sensor frame) through the stages with a stamp after each:
    ``({component: ms}, detections)``. ``faults``: add each component's page faults (:func:`page_faults`, read
    just after its stamp; ``total`` too) to this dict."""
    stamps: list[float] = []
    counts: list[int] = []

    def stamp() -> None:
        synchronize(device)
        stamps.append(time.perf_counter())
        if faults is not None:
            counts.append(page_faults())

    stamp()
    pts = torch.from_numpy(points).to(device)
    stamp()
    voxels = model.voxelize([pts])
    features, coords = model.pillar_net(voxels)
    stamp()
    x = model.feature_net(features, coords, voxels.batch_size)
    stamp()
    x, active = model.backbone_neck(x)
    stamp()
    out = model.head(x, active)
    stamp()
    dets = model.postprocess(out.cls, out.reg, out.dir)
    stamp()
    if faults is not None:
        for i, k in enumerate(COMPONENTS[:-1]):
            faults[k] = faults.get(k, 0) + counts[i + 1] - counts[i]
        faults["total"] = faults.get("total", 0) + counts[-1] - counts[0]
    return stamps_to_ms(stamps), int(sum(int(d.boxes.shape[0]) for d in dets))


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
        synchronize(device)
        t0 = time.perf_counter()
        outs[j] = models[j].head(*necks[j])
        synchronize(device)
        ms[j, 0] = (time.perf_counter() - t0) * 1e3
    for j in order:
        out = outs[j]
        synchronize(device)
        t0 = time.perf_counter()
        models[j].postprocess(out.cls, out.reg, out.dir)
        synchronize(device)
        ms[j, 1] = (time.perf_counter() - t0) * 1e3
    return ms
