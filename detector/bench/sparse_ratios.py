"""Dense vs sparse timings from one run (``tools/bench_sparse.py``): one SubM conv, the full backbone + neck, the whole
detector end to end, a training step and the conv forms (:mod:`detector.bench.conv_forms`); a closing summary gives
the four ratios the sparse model's targets are set on (:data:`TARGETS`).

Protocol (reference note, section 7): CPU, ``threads`` torch threads, batch 1, eval mode and ``torch.no_grad`` for
the inference rows, warm-up first, then ``repeats`` interleaved dense / sparse runs
(:func:`detector.bench.timing.time_calls`); each row has min and median wall time, CPU time (ms), page faults per run
and the ratio dense / sparse of the minima. The "backbone" rows are the paper's Backbone timer: from the pseudo-image
(dense canvas or SparseTensor) to the dense (1, 384, ny/2, nx/2) map, todense and concat included; the sparse rows
build their neighbour tables inside the timed region.

The "end to end" rows run the models that :func:`detector.models.build_model` builds from ``detector/configs/
mpchair_dense.yaml`` and ``mpchair_sparse.yaml`` (with ``head: sparse_exact``, and once more with its dense head for
reference), random weights, on one synthetic Matterport-Chair-like frame (:func:`matterport_points`): 21,095 points
(the mp3d-depth90 ray count) in clustered pillars at 0.75 % of the 768 x 512 canvas. Every stage of
:func:`detector.bench.timing.time_frame` is timed. ``score_thr`` is set to 0 so that NMS runs on the ``nms_pre`` = 100
top boxes as it would with a trained model (random weights score every anchor about 0.01, below the configured 0.1).

The glibc allocator and OpenMP's wait policy can dominate these timings; both are read only when a process starts, so
the caller chooses them before (``tools/bench_sparse.py`` re-runs itself under them with
:func:`detector.device.rerun_under`), and :func:`run_header` records the setting in force.
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import nn

from detector.bench.conv_forms import bench_forms, bench_forms_real, format_forms, make_sites
from detector.bench.timing import COMPONENTS, time_calls, time_frame
from detector.config import CONFIG_DIR, load_experiment
from detector.data.experiment import open_split
from detector.device import MALLOC_ENV, allocator_setting, use_device
from detector.models import build_model
from detector.models.backbone import SecondBackbone
from detector.models.head import AnchorHead, SparseExactHead
from detector.models.neck import SecondFPN
from detector.models.sparse_backbone import SparseBackboneNeck
from detector.sparse import SparseTensor, SubMConv2d, Workspace
from detector.sparse.conv import GEMM_MIN_FILL
from detector.sparse.synthetic import clustered_sites, mean_active_neighbours
from mpchair.core.errors import InputError

#: The sections a run can skip, in the order they run.
SECTIONS = ("subm", "backbone", "e2e", "train", "forms")
#: The targets: (section, row, label, minimum ratio dense / sparse).
TARGETS = (
    ("backbone", "matterport", "(a) backbone + neck, Matterport 768x512 clustered 0.75%", 15.0),
    ("e2e", "sparse+sparse_exact", "(b) end to end, sparse with head: sparse_exact", 10.0),
    ("backbone", "kitti", "(c) backbone + neck, KITTI 504x440 clustered 2.5%", 3.0),
    ("train", "dense head", "(d) training step fwd + bwd, Matterport clustered 0.75%", 3.0),
)


@dataclasses.dataclass(frozen=True)
class RatioOptions:
    """What one run times: ``threads`` torch threads, ``repeats`` timed rounds of the inference rows and
    ``train_repeats`` of the training step, the :data:`SECTIONS` to ``skip``; ``data`` (a KITTI-format dataset, or
    None) adds the forms on its first ``frames`` test frames."""

    threads: int = 2
    repeats: int = 5
    train_repeats: int = 3
    skip: frozenset[str] = frozenset()
    data: Path | None = None
    frames: int = 8


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
        r = time_calls(fns, repeats)
    table = convs["auto"].table(x)
    return {
        "case": f"{pattern} {100 * density:.2f}%",
        "active": int(coords.shape[0]),
        "neighbours": round(mean_active_neighbours(coords, shape), 2),
        "fill": round(table.fill, 3),
        "auto_algorithm": "gemm" if table.fill >= GEMM_MIN_FILL else "rulebook",
        "timings": r,
    }


def dense_backbone_neck() -> nn.Module:
    """The dense SECOND backbone + FPN of detector.models (3x3 stride-2 down-convs), eval mode."""
    backbone = SecondBackbone(
        in_channels=64, layer_channels=(64, 128, 256), layer_nums=(3, 5, 5), layer_strides=(2, 2, 2)
    )
    neck = SecondFPN(in_channels=(64, 128, 256), out_channels=(128, 128, 128), upsample_strides=(1, 2, 4))
    return nn.Sequential(backbone, neck)


def active_counts(model: SparseBackboneNeck, x: SparseTensor) -> list[int]:
    """Active sites after each block of the sparse backbone on ``x``."""
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
            r = time_calls(fns, repeats)
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
    """Points → detections with the models built from the Matterport configs (``detector.bench.timing.time_frame``):
    one row with every model's timings, its stage minima (ms) and detections."""
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

    warm = 1  # time_calls runs every function once as warm-up; drop those stage samples
    r = time_calls({k: (lambda k=k: run(k)) for k in models}, repeats, warmup=warm)
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

    r = time_calls({"dense": step_dense, "sparse": step_sparse, "sparse_canvas": step_sparse_canvas}, repeats)
    rx = time_calls({"dense": step_dense, "sparse": step_sparse_exact}, repeats)
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


def format_rows(title: str, rows: list[dict[str, object]]) -> str:
    """The rows under a ``## title`` heading: stage minima where timed, then per run wall min / median, CPU min, page
    faults and the dense / this ratios of the minima."""
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


def format_summary(rows: list[dict[str, object]], header: dict[str, object]) -> str:
    """The Targets block: each target's wall and CPU ratio, its minimum and met / MISSED."""
    lines = [f"\n## Targets (dense / sparse of the minima; {header['threads']} threads, batch 1, allocator "
             f"{'reuse' if header['allocator_reuse'] else 'default'}, OMP_WAIT_POLICY {header['omp_wait_policy']})"]
    for r in rows:
        lines.append(f"  {r['target']:<62s} wall {r['wall']:6.2f}x  cpu {r['cpu']:6.2f}x  target >= {r['min_ratio']:g}x"
                     f"  {'met' if r['met'] else 'MISSED'}")
    return "\n".join(lines)


def run_header(threads: int) -> dict[str, object]:
    """What the timings depend on, recorded first: torch, threads, CPUs, load average, the glibc allocator variables
    (:data:`detector.device.MALLOC_ENV`) and OpenMP's wait policy in force."""
    return {
        "torch": torch.__version__,
        "threads": threads,
        "cpus": os.cpu_count(),
        "machine": platform.machine(),
        "load_average": os.getloadavg(),
        "allocator": {k: os.environ.get(k, "(unset)") for k in MALLOC_ENV},
        "allocator_reuse": allocator_setting() == "reuse",
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "(unset)"),
    }


def _say(text: str) -> None:
    print(text, flush=True)  # each table as soon as it is timed: a run takes minutes


def run_sparse_ratios(opts: RatioOptions, emit: Callable[[str], None] = _say) -> dict[str, object]:
    """Every section not skipped, in :data:`SECTIONS` order, each one's table passed to ``emit`` as soon as it is
    timed, then the Targets block: ``{"header", <section>: rows, "forms_real" (with ``data``), "load_average_end",
    "summary"}`` (the ``--json-out`` file of ``tools/bench_sparse.py``). Bad options raise :class:`InputError`."""
    if opts.repeats < 1 or opts.train_repeats < 1 or opts.frames < 1:
        raise InputError(f"--repeats, --train-repeats and --frames must be >= 1, got {opts.repeats}, "
                         f"{opts.train_repeats}, {opts.frames}")
    unknown = sorted(set(opts.skip) - set(SECTIONS))
    if unknown:
        raise InputError(f"--skip: unknown sections {unknown} (choose from {', '.join(SECTIONS)})")
    if opts.data is not None and "forms" not in opts.skip:  # a bad --data fails now, not after minutes of timings
        open_split(load_experiment(CONFIG_DIR / "mpchair_sparse.yaml"), opts.data, "test")
    use_device("cpu", opts.threads)
    torch.manual_seed(0)
    header = run_header(opts.threads)
    emit("# bench_sparse " + json.dumps(header))
    results: dict[str, object] = {"header": header}
    sections = (
        ("subm", "One SubM 3x3 conv, 64 -> 64, 768 x 512 (eval, no_grad)", bench_subm, opts.repeats),
        ("backbone", "Backbone + neck to the dense 384-ch map (eval, no_grad)", bench_backbone, opts.repeats),
        ("e2e", "End to end: voxelize -> pillar net -> backbone -> head -> decode + NMS (eval, no_grad)",
         bench_end_to_end, opts.repeats),
        ("train", "Training step, forward + backward", bench_train_step, opts.train_repeats),
    )
    for key, title, fn, reps in sections:
        if key in opts.skip:
            continue
        rows = fn(reps)
        results[key] = rows
        emit(format_rows(title, rows))
    if "forms" not in opts.skip:
        forms: list[tuple[str, str, Callable[[int], list[dict[str, object]]]]] = [
            ("forms", "One GEMM form vs rulebook per conv kind (eval, no_grad, workspace)", bench_forms)]
        if opts.data is not None:
            data = opts.data
            forms.append(("forms_real", "The same on real frames: the whole sparse backbone, one kind forced",
                          lambda reps: bench_forms_real(reps, data, opts.frames)))
        for key, title, fn in forms:
            results[key] = fn(opts.repeats)
            emit(format_forms(title, results[key]))  # type: ignore[arg-type]
    results["load_average_end"] = os.getloadavg()
    results["summary"] = summary(results)
    emit(format_summary(results["summary"], header))  # type: ignore[arg-type]
    emit(f"\n# load average at the end: {results['load_average_end']}")
    return results
