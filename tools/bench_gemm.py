"""What routing the inference GEMMs through oneDNN buys (``detector.ops.gemm``): MKL against oneDNN, side by side in
one process, on the models' own GEMM shapes and on whole models.

    PYTHONPATH=. .venv/bin/python tools/bench_gemm.py --config detector/configs/mpchair_dense.yaml \\
        --config detector/configs/mpchair_sparse_exact.yaml --checkpoint DENSE.pt --checkpoint SPARSE.pt \\
        --data DATASET --split test --frames 10 --trials 3 --threads 2 [--json-out out.json]

1. **shapes**: ``x @ w.t()`` for the GEMMs of the Matterport models (the sparse SubM blocks, the neck levels, the
   dense neck), each in MKL (``torch.mm``) and in oneDNN (``torch.ops.mkldnn._linear_pointwise``), alternating;
   the minimum wall time and the CPU time of ``--repeats`` calls.
2. **models**: every ``--config`` (with its ``--checkpoint``, ``-`` = random weights) on the first ``--frames``
   frames of ``--split``, each frame through every model once with ``detector.ops.gemm.gemm_backend("mkl")`` and once
   with ``"auto"`` (oneDNN), the order alternating per frame; the stages of ``detector bench``
   (:func:`detector.bench.timing.time_frame`) with each model's inference workspace, mean ms per frame, and the
   first model / each other ratios of Backbone and Total under each library.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from detector.bench.run import bench_checkpoints, density_summary
from detector.bench.timing import COMPONENTS, time_frame
from detector.checkpoint import load_model
from detector.config import load_experiment, pseudoimage_geometry
from detector.data.experiment import load_eval_frames
from detector.device import machine_info, use_device
from detector.ops import gemm
from detector.sparse.workspace import Workspace
from mpchair.core.atomic import check_writable, write_text
from mpchair.core.clitools import run_script
from mpchair.core.errors import InputError
from mpchair.geometry import frame_density

#: (rows, K, O) of the Matterport models' GEMMs at D about 0.008 (sites per level from real frames).
SHAPES: tuple[tuple[str, int, int, int], ...] = (
    ("sparse SubM block 1", 1200, 576, 64),
    ("sparse SubM block 2", 400, 1152, 128),
    ("sparse SubM block 3", 150, 2304, 256),
    ("sparse neck level 3 (s=4)", 150, 256, 2048),
    # the dense neck runs a level 4 MiB of products at a time (detector.models.neck.CHUNK_BYTES): one chunk each
    ("dense neck level 1 (u=1), one chunk", 8192, 64, 128),
    ("dense neck level 2 (u=2), one chunk", 2048, 128, 512),
    ("dense neck level 3 (u=4), one chunk", 512, 256, 2048),
)
BACKENDS = ("mkl", "auto")


def time_shapes(repeats: int) -> list[dict]:
    """Per shape, each library's minimum wall and mean CPU ms of one call, the libraries alternating."""
    out = []
    for name, m, k, o in SHAPES:
        g = torch.Generator().manual_seed(m + k + o)
        x, w = torch.randn(m, k, generator=g), torch.randn(o, k, generator=g)
        calls = {"mkl": lambda x=x, w=w: torch.mm(x, w.t()),
                 "onednn": lambda x=x, w=w: torch.ops.mkldnn._linear_pointwise(x, w, None, "none", [], "")}
        wall = {n: [] for n in calls}
        cpu = dict.fromkeys(calls, 0.0)
        for f in calls.values():
            f()
        for _ in range(repeats):
            for n, f in calls.items():
                c0, t0 = time.process_time(), time.perf_counter()
                f()
                wall[n].append(time.perf_counter() - t0)
                cpu[n] += time.process_time() - c0
        gflop = 2 * m * k * o / 1e9
        out.append({"name": name, "shape": [m, k, o], "gflop": gflop,
                    **{f"{n}_min_ms": min(v) * 1e3 for n, v in wall.items()},
                    **{f"{n}_cpu_ms": cpu[n] / repeats * 1e3 for n in calls}})
    return out


def time_new_shapes(repeats: int) -> dict:
    """oneDNN's kernel per shape: ms per call of (m, 576) x (576, 64) with a row count it has not seen (m = 1000,
    1001, ...) against the same calls at one cached row count (mean of ``repeats`` calls each)."""
    lp = torch.ops.mkldnn._linear_pointwise
    w = torch.randn(64, 576)
    xs = [torch.randn(2000 + i, 576) for i in range(repeats)]  # row counts no other row of this bench used
    lp(xs[0], w, None, "none", [], "")
    t0 = time.perf_counter()
    for x in xs[1:]:
        lp(x, w, None, "none", [], "")
    new = (time.perf_counter() - t0) / (len(xs) - 1) * 1e3
    t0 = time.perf_counter()
    for _ in xs[1:]:
        lp(xs[0], w, None, "none", [], "")
    cached = (time.perf_counter() - t0) / (len(xs) - 1) * 1e3
    return {"shape": "(2000.., 576) x (576, 64)", "new_shape_ms": new, "cached_ms": cached}


def time_models(configs: list[str], checkpoints: list[str | None], data: Path, split: str, frames: int,
                trials: int, device: torch.device) -> tuple[list[dict], dict]:
    """Mean ms per stage of every model under each library, interleaved per frame (the module docstring), and the
    density D of the first model's frames (:func:`detector.bench.run.density_summary`)."""
    cfgs = [load_experiment(c) for c in configs]
    nets = [load_model(c, k, device) for c, k in zip(cfgs, checkpoints)]
    for net in nets:
        net.workspace = Workspace()
    clouds = [[f.points for f in load_eval_frames(c, data, split, frames)] for c in cfgs]
    geometry = pseudoimage_geometry(cfgs[0].model)
    density = density_summary([frame_density(p, geometry)[2] for p in clouds[0]])
    runs = [(j, b) for j in range(len(nets)) for b in BACKENDS]
    ms = np.zeros((len(runs), trials, len(clouds[0]), len(COMPONENTS)))
    for i in range(min(2, len(clouds[0]))):  # warm-up: kernels, caches, workspaces
        for j, b in runs:
            with gemm.gemm_backend(b):
                time_frame(nets[j], clouds[j][i], device)
    for t in range(trials):
        for i in range(len(clouds[0])):
            order = list(range(len(runs))) if (t + i) % 2 == 0 else list(reversed(range(len(runs))))
            for r in order:
                j, b = runs[r]
                with gemm.gemm_backend(b):
                    stages, _ = time_frame(nets[j], clouds[j][i], device)
                ms[r, t, i] = [stages[k] for k in COMPONENTS]
    means = ms.mean(axis=(1, 2))
    return [{"config": configs[j], "weights": checkpoints[j] or "random", "gemm": "mkl" if b == "mkl" else "onednn",
             "mean_ms": dict(zip(COMPONENTS, map(float, means[r])))} for r, (j, b) in enumerate(runs)], density


def format_result(result: dict) -> str:
    """Markdown: the shapes table, the models table, the first model / each other ratios per library."""
    lines = ["| GEMM (rows x K x O) | GFLOP | MKL ms (CPU ms) | oneDNN ms (CPU ms) | MKL / oneDNN |",
             "|---|---|---|---|---|"]
    for s in result["shapes"]:
        m, k, o = s["shape"]
        lines.append(f"| {s['name']} ({m} x {k} x {o}) | {s['gflop']:.3f} | {s['mkl_min_ms']:.3f} "
                     f"({s['mkl_cpu_ms']:.3f}) | {s['onednn_min_ms']:.3f} ({s['onednn_cpu_ms']:.3f}) | "
                     f"{s['mkl_min_ms'] / s['onednn_min_ms']:.2f}x |")
    ns = result["new_shapes"]
    lines.append(f"| new shape: oneDNN {ns['shape']}, a row count not seen before / one seen | | | "
                 f"{ns['new_shape_ms']:.3f} / {ns['cached_ms']:.3f} | |")
    models = result["models"]
    if models:
        lines += ["", "| model | GEMM library | Feature Extract | Backbone | Head | Total |",
                  "|---|---|---|---|---|---|"]
        for r in models:
            ms = r["mean_ms"]
            lines.append(f"| {Path(r['config']).stem} | {r['gemm']} | {ms['feature_extract']:.1f} | "
                         f"{ms['backbone']:.1f} | {ms['head']:.1f} | {ms['total']:.1f} |")
        lines += ["", "| ratio | GEMM library | Backbone | Total |", "|---|---|---|---|"]
        for lib in ("mkl", "onednn"):
            rows = [r for r in models if r["gemm"] == lib]
            for r in rows[1:]:
                a, b = rows[0]["mean_ms"], r["mean_ms"]
                lines.append(f"| {Path(rows[0]['config']).stem} / {Path(r['config']).stem} | {lib} (both sides) | "
                             f"{a['backbone'] / b['backbone']:.1f}x | {a['total'] / b['total']:.1f}x |")
    mach, dens = result["machine"], result["density"]
    lines += ["", ("Both sides eager PyTorch fp32 with their inference workspaces; " if models else "")
              + f"{mach['cpu']}; {mach['torch_threads']} torch threads; allocator {mach['allocator']}; load average "
              f"(1 min) {mach['loadavg_1m']}."]
    if dens is not None:
        lines.append(f"Density D (pillars / canvas cells) of the frames: median {dens['median']:.5f}, min "
                     f"{dens['min']:.5f}, max {dens['max']:.5f} over {dens['frames']} frames.")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the bench; 2 with one ``error:`` line on bad input."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", action="append", default=[], help="experiment YAML (repeat; the first is the "
                   "ratios' numerator); none: the shapes only")
    p.add_argument("--checkpoint", action="append", default=[], help="weights per --config ('-': random)")
    p.add_argument("--data", type=Path, default=None, help="KITTI-format dataset folder (with --config)")
    p.add_argument("--split", default="test")
    p.add_argument("--frames", type=int, default=10)
    p.add_argument("--trials", type=int, default=3)
    p.add_argument("--repeats", type=int, default=20, help="calls per GEMM shape and library")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json-out", type=Path, default=None, help="also write the result here")
    args = p.parse_args(argv)
    return run_script(lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    try:
        if not gemm.HAVE_ONEDNN:
            raise InputError("this torch build has no oneDNN (torch.backends.mkldnn): nothing to compare")
        if args.config and args.data is None:
            raise InputError("--config needs --data")
        ckpts = bench_checkpoints(args.config, args.checkpoint)
        if args.frames < 1 or args.trials < 1 or args.repeats < 1:
            raise InputError("--frames, --trials and --repeats must be >= 1")
        if args.json_out is not None:
            check_writable(args.json_out)
        device = use_device("cpu", args.threads)
        with torch.no_grad():
            shapes = time_shapes(args.repeats)
            new_shapes = time_new_shapes(max(2, args.repeats))
            models, density = time_models(args.config, ckpts, args.data, args.split, args.frames, args.trials,
                                          device) if args.config else ([], None)
    except (InputError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    result = {"shapes": shapes, "new_shapes": new_shapes, "models": models, "density": density,
              "machine": {**machine_info(device), "gemm": "both"},
              "protocol": {"data": str(args.data), "split": args.split, "frames": args.frames, "trials": args.trials,
                           "repeats": args.repeats, "interleaved": True, "batch_size": 1}}
    if args.json_out is not None:
        write_text(args.json_out, json.dumps(result, indent=2) + "\n")
    print(format_result(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
