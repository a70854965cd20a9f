"""Dense vs sparse timings from one run: one SubM conv, the full backbone + neck, the whole detector end to end, and a
training step; a closing summary prints the four ratios the issue sets targets for.

Protocol (reference note, section 7): CPU, ``torch.set_num_threads(--threads)`` (2), batch 1, eval mode and
``torch.no_grad`` for the inference rows, warm-up first, then ``--repeats`` interleaved dense/sparse runs; the tables
show min and median wall time (ms) and the ratio dense / sparse of the minima. The "backbone" rows are the paper's
Backbone timer: from the pseudo-image (dense canvas or SparseTensor) to the dense (1, 384, ny/2, nx/2) map, todense and
concat included; the sparse rows build their neighbour tables inside the timed region.

The "end to end" rows run the models that ``detector.models.build_model`` builds from ``detector/configs/
mpchair_dense.yaml`` and ``mpchair_sparse.yaml`` (with ``head: sparse_exact``, and once more with its dense head for
reference), random weights, on one synthetic Matterport-Chair-like frame: 21,095 points (the mp3d-depth90 ray count)
in clustered pillars at 0.75 % of the 768 x 512 canvas. Every stage of ``detector.bench.timing.time_frame`` is timed:
voxelize + pillar net, scatter / SparseTensor, backbone + neck, head, decode + rotated NMS. ``score_thr`` is set to 0
for the benchmark so that NMS runs on the ``nms_pre`` = 100 top boxes as it would with a trained model (random weights
score every anchor about 0.01, below the configured 0.1).

The allocator can dominate CPU timings (reference note, timing note): glibc returns big freed buffers to the OS, so
every dense forward pays page faults. Run once as is and once with ``--reuse-allocator`` (re-executes itself with
``MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=68719476736``); the header prints the setting in force and every row its
minor page faults per run.

On a machine whose cores are busy with other jobs, OpenMP's default spin-waiting can wreck the 2-thread rows: each
parallel region waits for a worker thread that is not scheduled while the waiting thread spins. The sparse model runs
hundreds of small parallel ops per forward, so it suffers most (measured: 4.6 s instead of 0.1 s per sparse backbone
forward with another 2-thread job running; the dense model loses far less). ``--omp-passive`` re-executes under
``OMP_WAIT_POLICY=PASSIVE`` (idle threads sleep at once) for such machines; the header prints the setting.

The "forms" rows time each sparse conv kind (SubM, 2x2 and 9x9 down, s = 2 / 4 transposed) in its one-GEMM form
against its rulebook form and the ``auto`` pick, on clustered and uniform sites (the SubMs also forward + backward,
``*_train``); with ``--data`` also the whole sparse backbone on real frames with every conv of one kind forced to
each form (docs/sparse.md, "Compute").

    PYTHONPATH=. .venv/bin/python tools/bench_sparse.py [--threads 2] [--repeats 5] [--json-out out.json]
        [--skip subm forms backbone e2e train] [--data DATASET [--frames 8]] [--reuse-allocator] [--omp-passive]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import resource
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import nn

from detector.bench.timing import COMPONENTS, time_frame
from detector.checkpoint import load_model
from detector.config import CONFIG_DIR, load_experiment
from detector.data.experiment import load_eval_frames
from detector.device import MALLOC_REUSE
from detector.models import build_model
from detector.models.backbone import SecondBackbone
from detector.models.head import AnchorHead, SparseExactHead
from detector.models.neck import SecondFPN
from detector.models.sparse_backbone import SparseBackboneNeck
from detector.sparse import SparseConv2d, SparseConvTranspose2d, SparseTensor, SubMConv2d, Workspace
from detector.sparse.conv import GEMM_MIN_FILL
from detector.sparse.indices import down_table
from detector.sparse.synthetic import clustered_sites, mean_active_neighbours, uniform_sites
from mpchair.core.atomic import write_text

PASSIVE_ENV = {"OMP_WAIT_POLICY": "PASSIVE"}
#: The issue's targets: (section, row, label, minimum ratio dense / sparse).
TARGETS = (
    ("backbone", "matterport", "(a) backbone + neck, Matterport 768x512 clustered 0.75%", 15.0),
    ("e2e", "sparse+sparse_exact", "(b) end to end, sparse with head: sparse_exact", 10.0),
    ("backbone", "kitti", "(c) backbone + neck, KITTI 504x440 clustered 2.5%", 3.0),
    ("train", "dense head", "(d) training step fwd + bwd, Matterport clustered 0.75%", 3.0),
)


def timed(fn: Callable[[], object]) -> tuple[float, float, int]:
    """Wall seconds, process CPU seconds (all threads, user + system) and minor page faults of one call.

    On a shared machine the CPU time is the steadier measure of the work done; the wall time is what a dedicated
    machine would show only when the CPU is not oversubscribed.
    """
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    c0, t0 = time.process_time(), time.perf_counter()
    fn()
    dt, dc = time.perf_counter() - t0, time.process_time() - c0
    return dt, dc, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0


def compare(fns: dict[str, Callable[[], object]], repeats: int, warmup: int = 1) -> dict[str, dict[str, float]]:
    """Interleaved runs of every function; per name: wall min/median ms, CPU min ms, mean page faults per run."""
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    samples: dict[str, list[tuple[float, float, int]]] = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            samples[k].append(timed(fn))
    return {
        k: {
            "min_ms": 1e3 * min(t for t, _, _ in v),
            "median_ms": 1e3 * statistics.median(t for t, _, _ in v),
            "cpu_min_ms": 1e3 * min(c for _, c, _ in v),
            "faults": statistics.mean(f for _, _, f in v),
        }
        for k, v in samples.items()
    }


def make_sites(pattern: str, shape: tuple[int, int], density: float, seed: int) -> torch.Tensor:
    return (clustered_sites if pattern == "clustered" else uniform_sites)(shape, density, seed=seed)


def bench_subm(repeats: int) -> list[dict[str, object]]:
    """One SubM 3x3 64 → 64 conv at 768 x 512: dense Conv2d vs the sparse conv (tables cached / built in the run)."""
    dense = nn.Conv2d(64, 64, 3, padding=1, bias=False).eval()
    cases = (("clustered", 0.0075), ("clustered", 0.025), ("uniform", 0.0075))
    return [_subm_case(dense, pattern, density, repeats) for pattern, density in cases]


def _subm_case(dense: nn.Conv2d, pattern: str, density: float, repeats: int) -> dict[str, object]:
    shape = (768, 512)
    coords = make_sites(pattern, shape, density, seed=1)
    feats = torch.randn(coords.shape[0], 64)
    x = SparseTensor(feats, coords, shape, 1)
    canvas = x.dense()
    convs = {a: SubMConv2d(64, 64, 3, indice_key="k", algorithm=a).eval() for a in ("gemm", "rulebook", "auto")}
    for c in convs.values():
        c.weight.data.copy_(dense.weight.data)
    fns: dict[str, Callable[[], object]] = {"dense": lambda: dense(canvas)}
    for a, c in convs.items():
        fns[f"sparse_{a}"] = lambda c=c: c(x)
    fns["sparse_auto+table"] = lambda: convs["auto"](SparseTensor(feats, coords, shape, 1))
    with torch.no_grad():
        r = compare(fns, repeats)
    table = convs["auto"].table(x)
    return {
        "case": f"{pattern} {100 * density:.2f}%",
        "active": int(coords.shape[0]),
        "neighbours": round(mean_active_neighbours(coords, shape), 2),
        "fill": round(table.fill, 3),
        "auto_algorithm": "gemm" if table.fill >= GEMM_MIN_FILL else "rulebook",
        "timings": r,
    }


ALGORITHMS = ("gemm", "rulebook", "auto")
#: (kind, grid, pattern, density, in, out, kernel, stride) of the conv shapes the Matterport model runs: SubMs at
#: block 1 (384 x 256, 64 ch) and block 3 (96 x 64, 256 ch), the 2x2 and the 9x9 stride-2 down-convs on the pillar
#: grid, the neck's s = 2 and s = 4 transposed convs onto the block-1 set.
FORM_CASES = (
    ("subm", (384, 256), "clustered", 0.013, 64, 64, 3, 1),
    ("subm", (384, 256), "uniform", 0.013, 64, 64, 3, 1),
    ("subm", (96, 64), "clustered", 0.02, 256, 256, 3, 1),
    ("subm", (96, 64), "uniform", 0.02, 256, 256, 3, 1),
    ("down", (768, 512), "clustered", 0.0075, 64, 64, 2, 2),
    ("down", (768, 512), "uniform", 0.0075, 64, 64, 2, 2),
    ("wide_down", (768, 512), "clustered", 0.0075, 64, 64, 9, 2),
    ("wide_down", (768, 512), "uniform", 0.0075, 64, 64, 9, 2),
    ("up", (384, 256), "clustered", 0.013, 128, 128, 2, 2),
    ("up", (384, 256), "uniform", 0.013, 128, 128, 2, 2),
    ("up", (384, 256), "clustered", 0.013, 256, 128, 4, 4),
    ("up", (384, 256), "uniform", 0.013, 256, 128, 4, 4),
)


def bench_forms(repeats: int) -> list[dict[str, object]]:
    """Each conv kind in its one-GEMM form vs its rulebook (and the ``auto`` pick), inference with a workspace, on
    clustered and uniform sites (``detector.sparse.synthetic``), interleaved."""
    rows = []
    for kind, shape, pattern, density, cin, cout, k, s in FORM_CASES:
        coords = make_sites(pattern, shape, density, seed=5)
        ws = Workspace()
        x = SparseTensor(torch.randn(coords.shape[0], cin).relu(), coords, shape, 1, workspace=ws, origin="input")
        if kind == "up":  # the coarse input is the site set a down-conv of the target gives
            t = down_table(coords, shape, s)
            coarse = SparseTensor(torch.randn(t.out_coords.shape[0], cin), t.out_coords, t.out_shape, 1,
                                  workspace=ws, origin="coarse")
            mods = {a: SparseConvTranspose2d(cin, cout, k, s, algorithm=a) for a in ALGORITHMS}
            fns = {a: (lambda m=m, c=coarse, x=x: m(c, x)) for a, m in mods.items()}
            fill = float((t.in_rows.numel()) / max(1, t.out_coords.shape[0] * s * s))
        elif kind == "subm":
            mods = {a: SubMConv2d(cin, cout, k, indice_key="k", algorithm=a) for a in ALGORITHMS}
            fns = {a: (lambda m=m, x=x: m(x)) for a, m in mods.items()}
            fill = mods["auto"].table(x).fill
        else:
            mods = {a: SparseConv2d(cin, cout, k, s, algorithm=a) for a in ALGORITHMS}
            fns = {a: (lambda m=m, x=x: m(x)) for a, m in mods.items()}
            fill = None
        for m in mods.values():
            m.eval().load_state_dict(mods["auto"].state_dict())
        with torch.no_grad():
            r = compare(fns, repeats)
        if kind == "subm":  # training: forward + backward of the layer (no workspace), input gradient included
            xt = SparseTensor(x.features.clone().requires_grad_(True), coords, shape, 1)
            g = torch.randn(coords.shape[0], cout)
            r.update(compare({f"{a}_train": (lambda m=mods[a], xt=xt, g=g: m(xt).features.backward(g))
                              for a in ("gemm", "rulebook")}, repeats))
        rows.append({"case": f"{kind} {k}x{k}/s{s} {cin}->{cout} {shape[0]}x{shape[1]} {pattern} {100 * density:.2f}%",
                     "active": int(coords.shape[0]), "fill": None if fill is None else round(fill, 3), "timings": r})
    return rows


def bench_forms_real(repeats: int, data: Path, frames: int) -> list[dict[str, object]]:
    """The Matterport sparse backbone on real frames (``mpchair_sparse.yaml``, random weights, workspace) with every
    conv of one kind forced to each form: whole-backbone ms per frame, interleaved."""
    cfg = load_experiment(CONFIG_DIR / "mpchair_sparse.yaml")
    model = load_model(cfg, None, torch.device("cpu"), seed=0).eval()
    model.workspace = Workspace()
    with torch.no_grad():
        inputs = [model.pillar_net(model.voxelize([torch.from_numpy(f.points)]))
                  for f in load_eval_frames(cfg, data, "test", frames)]
    rows = []
    for kind, types in (("subm", SubMConv2d), ("down", SparseConv2d), ("up", SparseConvTranspose2d)):
        mods = [m for m in model.modules() if isinstance(m, types)]

        def run(a: str, mods: list[nn.Module] = mods) -> None:
            for m in mods:
                m.algorithm = a
            for f, c in inputs:
                model.backbone_neck(model.feature_net(f, c, 1))

        with torch.no_grad():
            r = compare({a: (lambda a=a: run(a)) for a in ALGORITHMS}, repeats)
        for v in r.values():  # per frame
            for key in ("min_ms", "median_ms", "cpu_min_ms"):
                v[key] /= len(inputs)
        rows.append({"case": f"backbone on {len(inputs)} real frames of {data}, every {kind} conv forced",
                     "timings": r})
    return rows


def fmt_forms(title: str, rows: list[dict[str, object]]) -> str:
    lines = [f"\n## {title}"]
    for row in rows:
        t: dict[str, dict[str, float]] = row["timings"]  # type: ignore[assignment]
        extra = {k: v for k, v in row.items() if k not in ("case", "timings")}
        lines.append(f"{row['case']}  {extra}")
        for k, v in t.items():
            ratio = t["rulebook_train" if k.endswith("_train") else "rulebook"]["cpu_min_ms"] / v["cpu_min_ms"]
            lines.append(f"  {k:10s} wall min {v['min_ms']:8.3f} median {v['median_ms']:8.3f}  cpu min "
                         f"{v['cpu_min_ms']:8.3f} ms   rulebook / this (cpu) {ratio:5.2f}x")
    return "\n".join(lines)


def dense_backbone_neck() -> nn.Module:
    """The dense SECOND backbone + FPN of detector.models (3x3 stride-2 down-convs), eval mode."""
    backbone = SecondBackbone(
        in_channels=64, layer_channels=(64, 128, 256), layer_nums=(3, 5, 5), layer_strides=(2, 2, 2)
    )
    neck = SecondFPN(in_channels=(64, 128, 256), out_channels=(128, 128, 128), upsample_strides=(1, 2, 4))
    return nn.Sequential(backbone, neck)


def active_counts(model: SparseBackboneNeck, x: SparseTensor) -> list[int]:
    counts = []
    with torch.no_grad():
        for block in model.blocks:
            x = block(x)
            counts.append(x.num_active)
    return counts


def bench_backbone(repeats: int) -> list[dict[str, object]]:
    """Full backbone + neck up to the dense 384-channel map, each model with its inference workspace and without
    (``*_alloc``: every buffer allocated per frame, as before the workspace)."""
    dense = dense_backbone_neck().eval()
    backbone, neck = dense[0], dense[1]
    sparse = SparseBackboneNeck().eval()
    rows = []
    for name, shape, pattern, density in (
        ("matterport 768x512", (768, 512), "clustered", 0.0075),
        ("kitti 504x440", (504, 440), "clustered", 0.025),
    ):
        coords = make_sites(pattern, shape, density, seed=2)
        feats = torch.randn(coords.shape[0], 64).relu()  # pillar features come out of a ReLU
        # the model's inference canvas is channels-last (detector.models.scatter)
        canvas = SparseTensor(feats, coords, shape, 1).dense().contiguous(memory_format=torch.channels_last)
        ws_dense, ws_sparse = Workspace(), Workspace()
        fns = {
            "dense": lambda canvas=canvas, ws=ws_dense: neck(backbone(canvas), workspace=ws),
            "dense_alloc": lambda canvas=canvas: neck(backbone(canvas)),
            "sparse": lambda f=feats, c=coords, sh=shape, ws=ws_sparse: sparse(
                SparseTensor(f, c, sh, 1, workspace=ws, origin="input")),
            "sparse_alloc": lambda f=feats, c=coords, sh=shape: sparse(SparseTensor(f, c, sh, 1)),
        }
        with torch.no_grad():
            r = compare(fns, repeats)
        rows.append(
            {
                "case": f"{name} {pattern} {100 * density:.2f}%",
                "active": int(coords.shape[0]),
                "active_after_blocks": active_counts(sparse, SparseTensor(feats, coords, shape, 1)),
                "timings": r,
            }
        )
    return rows


def matterport_points(seed: int = 4, num_points: int = 21095, density: float = 0.0075) -> np.ndarray:
    """(N, 3) float32 sensor-frame points whose pillars are clustered sites of the Matterport canvas.

    The sites cover ``density`` of the padded 768 x 512 canvas but lie in the real 760 x 500 grid (points outside it
    are cropped by the voxelizer); every site gets at least one point, the rest are spread over the sites at random.
    """
    m = load_experiment(CONFIG_DIR / "mpchair_dense.yaml").model
    x0, y0, z0, x1, y1, z1 = m.point_cloud_range
    vx, vy = m.voxel_size[0], m.voxel_size[1]
    ny_real, nx_real = round((y1 - y0) / vy), round((x1 - x0) / vx)
    count = round(density * m.output_shape[0] * m.output_shape[1])
    sites = clustered_sites((ny_real, nx_real), count / (ny_real * nx_real), seed=seed).numpy()
    rng = np.random.default_rng(seed)
    pick = rng.integers(0, len(sites), num_points)
    pick[: len(sites)] = np.arange(len(sites))
    iy, ix = sites[pick, 1], sites[pick, 2]
    return np.stack(
        [x0 + (ix + rng.uniform(0.01, 0.99, num_points)) * vx, y0 + (iy + rng.uniform(0.01, 0.99, num_points)) * vy,
         rng.uniform(z0 + 0.01, z1 - 0.01, num_points)], axis=1,
    ).astype(np.float32)


def bench_end_to_end(repeats: int) -> list[dict[str, object]]:
    """Points → detections with the models built from the Matterport configs (``detector.bench.timing.time_frame``)."""
    dense_cfg = load_experiment(CONFIG_DIR / "mpchair_dense.yaml").model
    sparse_cfg = load_experiment(CONFIG_DIR / "mpchair_sparse.yaml").model
    variants = {
        "dense": dense_cfg,
        "sparse+sparse_exact": dataclasses.replace(sparse_cfg, head="sparse_exact"),
        "sparse+dense_head": dataclasses.replace(sparse_cfg, head="dense"),
        "dense_alloc": dense_cfg,
        "sparse+sparse_exact_alloc": dataclasses.replace(sparse_cfg, head="sparse_exact"),
    }
    models = {}
    for name, cfg in variants.items():
        torch.manual_seed(0)
        models[name] = build_model(dataclasses.replace(cfg, score_thr=0.0)).eval()
        if not name.endswith("_alloc"):  # *_alloc: without the inference workspace, as before it
            models[name].workspace = Workspace()
    points = matterport_points()
    device = torch.device("cpu")
    stages: dict[str, list[dict[str, float]]] = {k: [] for k in models}
    detections: dict[str, int] = {}

    def run(name: str) -> None:
        ms, n = time_frame(models[name], points, device)
        stages[name].append(ms)
        detections[name] = n

    r = compare({k: (lambda k=k: run(k)) for k in models}, repeats)
    warm = 1  # compare() runs every function once as warm-up; drop those stage samples
    n_sites = int(models["dense"].voxelize([torch.from_numpy(points)]).coords.shape[0])
    return [
        {
            "case": f"matterport 768x512, {len(points)} points, {n_sites} pillars "
                    f"({100 * n_sites / (768 * 512):.2f}%), configs mpchair_dense / mpchair_sparse",
            "detections": detections,
            "stages_min_ms": {
                k: {c: round(min(s[c] for s in v[warm:]), 2) for c in COMPONENTS} for k, v in stages.items()
            },
            "timings": r,
        }
    ]


def bench_train_step(repeats: int) -> list[dict[str, object]]:
    """Forward + backward of backbone + neck + the dense 1x1 head (as the reference's training-step rows)."""
    shape = (768, 512)
    coords = make_sites("clustered", shape, 0.0075, seed=3)
    feats = torch.randn(coords.shape[0], 64).relu()
    canvas = SparseTensor(feats, coords, shape, 1).dense()
    dense, sparse = dense_backbone_neck().train(), SparseBackboneNeck().train()
    head_d, head_s = (AnchorHead(in_channels=384, num_anchors=2, num_classes=1).train() for _ in range(2))
    head_x = SparseExactHead(in_channels=384, num_anchors=2, num_classes=1).train()

    def loss_of(out: tuple[torch.Tensor, ...]) -> torch.Tensor:
        return sum(o.square().mean() for o in out)  # type: ignore[return-value]

    def step_dense() -> None:
        loss_of(head_d(dense(canvas))).backward()

    def step_sparse() -> None:  # as PointPillars.forward trains it: the head on the neck's active rows
        loss_of(head_s.on_sites(sparse.neck_rows(SparseTensor(feats, coords, shape, 1)))).backward()

    def step_sparse_canvas() -> None:  # the head on the scattered canvas (before AnchorHead.on_sites)
        y, _ = sparse(SparseTensor(feats, coords, shape, 1))
        loss_of(head_s(y)).backward()

    def step_sparse_exact() -> None:
        y, active = sparse(SparseTensor(feats, coords, shape, 1))
        loss_of(head_x(y, active)).backward()

    r = compare({"dense": step_dense, "sparse": step_sparse, "sparse_canvas": step_sparse_canvas}, repeats)
    rx = compare({"dense": step_dense, "sparse": step_sparse_exact}, repeats)
    return [
        {
            "case": "matterport 768x512 clustered 0.75% fwd+bwd (+ dense head; sparse: on the neck rows as trained, "
                    "sparse_canvas: on the scattered canvas)",
            "active": int(coords.shape[0]),
            "timings": r,
        },
        {
            "case": "matterport 768x512 clustered 0.75% fwd+bwd (dense: dense head; sparse: head sparse_exact)",
            "active": int(coords.shape[0]),
            "timings": rx,
        },
    ]


def fmt_rows(title: str, rows: list[dict[str, object]]) -> str:
    lines = [f"\n## {title}"]
    for row in rows:
        t: dict[str, dict[str, float]] = row["timings"]  # type: ignore[assignment]
        extra = {k: v for k, v in row.items() if k not in ("case", "timings", "stages_min_ms")}
        lines.append(f"{row['case']}  {extra}")
        stages: dict[str, dict[str, float]] = row.get("stages_min_ms", {})  # type: ignore[assignment]
        for k, v in stages.items():
            lines.append(f"  {k:20s} stage minima (ms): " + ", ".join(f"{c} {ms:.2f}" for c, ms in v.items()))
        base, base_cpu = t["dense"]["min_ms"], t["dense"]["cpu_min_ms"]
        for k, v in t.items():
            ratio = "" if k == "dense" else f"  wall {base / v['min_ms']:6.1f}x  cpu {base_cpu / v['cpu_min_ms']:6.1f}x"
            lines.append(
                f"  {k:20s} wall min {v['min_ms']:9.2f} median {v['median_ms']:9.2f}  cpu min {v['cpu_min_ms']:9.2f} ms"
                f"  faults/run {v['faults']:7.0f}{ratio}"
            )
    return "\n".join(lines)


def summary(results: dict[str, object]) -> list[dict[str, object]]:
    """The targeted ratios (dense / sparse of the minima, wall and CPU) of the sections that ran."""
    out = []
    for section, row_key, label, target in TARGETS:
        rows = results.get(section)
        if not rows:
            continue
        for row in rows:  # type: ignore[union-attr]
            t = row["timings"]
            if row_key in row["case"] or row_key in t:
                sparse_key = row_key if row_key in t else "sparse"
                wall = t["dense"]["min_ms"] / t[sparse_key]["min_ms"]
                cpu = t["dense"]["cpu_min_ms"] / t[sparse_key]["cpu_min_ms"]
                out.append({"target": label, "min_ratio": target, "wall": round(wall, 2), "cpu": round(cpu, 2),
                            "met": wall >= target})
                break
    return out


def fmt_summary(rows: list[dict[str, object]], header: dict[str, object]) -> str:
    lines = [f"\n## Targets (dense / sparse of the minima; {header['threads']} threads, batch 1, allocator "
             f"{'reuse' if header['allocator_reuse'] else 'default'}, OMP_WAIT_POLICY {header['omp_wait_policy']})"]
    for r in rows:
        lines.append(f"  {r['target']:<62s} wall {r['wall']:6.2f}x  cpu {r['cpu']:6.2f}x  target >= {r['min_ratio']:g}x"
                     f"  {'met' if r['met'] else 'MISSED'}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--train-repeats", type=int, default=3)
    p.add_argument("--skip", nargs="*", default=[], choices=["subm", "forms", "backbone", "e2e", "train"])
    p.add_argument("--data", type=Path, default=None,
                   help="KITTI-format dataset: also time the forms on its first --frames test frames")
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--json-out", type=Path, default=None, help="also write the results as JSON to this path")
    p.add_argument("--reuse-allocator", action="store_true", help=f"re-run under {MALLOC_REUSE}")
    p.add_argument("--omp-passive", action="store_true", help=f"re-run under {PASSIVE_ENV} (busy machines)")
    args = p.parse_args(argv)
    want = {**(MALLOC_REUSE if args.reuse_allocator else {}), **(PASSIVE_ENV if args.omp_passive else {})}
    if any(os.environ.get(k) != v for k, v in want.items()):
        os.execve(sys.executable, [sys.executable, __file__, *sys.argv[1:]], {**os.environ, **want})

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    allocator = {k: os.environ.get(k, "(unset)") for k in MALLOC_REUSE}
    header = {
        "torch": torch.__version__,
        "threads": args.threads,
        "cpus": os.cpu_count(),
        "machine": platform.machine(),
        "load_average": os.getloadavg(),
        "allocator": allocator,
        "allocator_reuse": all(os.environ.get(k) == v for k, v in MALLOC_REUSE.items()),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "(unset)"),
    }
    print("# bench_sparse", json.dumps(header))
    results: dict[str, object] = {"header": header}
    sections = (
        ("subm", "One SubM 3x3 conv, 64 -> 64, 768 x 512 (eval, no_grad)", bench_subm, args.repeats),
        ("backbone", "Backbone + neck to the dense 384-ch map (eval, no_grad)", bench_backbone, args.repeats),
        ("e2e", "End to end: voxelize -> pillar net -> backbone -> head -> decode + NMS (eval, no_grad)",
         bench_end_to_end, args.repeats),
        ("train", "Training step, forward + backward", bench_train_step, args.train_repeats),
    )
    for key, title, fn, reps in sections:
        if key in args.skip:
            continue
        rows = fn(reps)
        results[key] = rows
        print(fmt_rows(title, rows), flush=True)
    if "forms" not in args.skip:
        forms = [("forms", "One GEMM form vs rulebook per conv kind (eval, no_grad, workspace)", bench_forms)]
        if args.data is not None:
            forms.append(("forms_real", "The same on real frames: the whole sparse backbone, one kind forced",
                          lambda reps: bench_forms_real(reps, args.data, args.frames)))
        for key, title, fn in forms:
            results[key] = fn(args.repeats)
            print(fmt_forms(title, results[key]), flush=True)
    results["load_average_end"] = os.getloadavg()
    results["summary"] = summary(results)
    print(fmt_summary(results["summary"], header))
    print(f"\n# load average at the end: {results['load_average_end']}")
    if args.json_out is not None:
        write_text(args.json_out, json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
