"""spconv 2.3 (its CPU build) beside our sparse engine on Sparse PointPillars' sparse blocks and backbone + neck: ms
per frame, exactness and run-to-run determinism, side by side in one process.

    PYTHONPATH=. .venv/bin/python tools/bench_spconv.py --config configs/models/mpchair_sparse.yaml \\
        [--checkpoint SPARSE.pt] (--data DATASET --split test | --density 0.0075) [--frames 10] [--trials 3] \\
        [--threads 1,2] [--exact-frames 1] [--json-out out.json]

Needs the ``spconv`` extra (``pip install -c constraints.txt -e '.[spconv]'``). The network is the config's sparse
backbone + neck with the checkpoint's weights (random, seeded, with seeded BatchNorm statistics, without one), rebuilt
in spconv with the same weights (``detector.bench.spconv_peer``). Frames: the first ``--frames`` frames of
``--split`` through the model's voxelizer and pillar net, or ``--density``: synthetic clustered sites on the
config's grid (``detector.bench.density.site_frames``). Per ``--threads`` value, every frame runs through four
timed calls, interleaved with the order reversed every other frame: ours and spconv on the three sparse blocks
("blocks"), ours and spconv on blocks + neck up to the 384-channel rows on the block-1 sites ("backbone+neck"; the
canvas scatter after it, the same for both, is left out); warm-up first, then ``--trials`` passes. Ours runs eager
with its inference workspace, as ``detector bench``; spconv as its ``nn.Module``s run. Times are float32.

Exactness (``--exact-frames`` first frames, at every thread count: spconv's results depend on it): max abs
difference per block and of the neck rows, float64 spconv vs ours and ours vs the masked dense-convolution chain,
and float32 each engine vs that float64 chain. Determinism: every timed call's outputs against the first call's of
the same frame and thread count (bitwise equal or not, and the largest difference). Numbers from a busy machine are
not runtimes: run it on a quiet one.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from detector.bench.run import density_summary
from detector.bench.spconv_peer import (
    SiteFrame,
    SpconvBackboneNeck,
    dataset_frames,
    exactness,
    import_spconv,
    our_blocks,
    our_input,
    randomise_batchnorm_,
    same_outputs,
    spconv_input,
    spconv_version,
    synthetic_frames,
)
from detector.checkpoint import load_model
from detector.config import load_experiment
from detector.device import load_1m, machine_info, oversubscription_warning, usable_cores, use_device
from detector.models.sparse_backbone import SparseBackboneNeck
from detector.sparse.workspace import Workspace
from mpchair.core.atomic import check_writable, write_text
from mpchair.core.clitools import run_script
from mpchair.core.errors import InputError


def _calls(ours: SparseBackboneNeck, peer: SpconvBackboneNeck, shape: tuple[int, int], ws: Workspace,
           origin: object) -> dict:
    """(engine, part) → f(frame) returning the call's output tensors (ours' live in its workspace: clone to keep);
    ``origin`` keys our input site set in the workspace (the model, as ``PointPillars.feature_net`` does)."""

    def ours_blocks(f: SiteFrame) -> list[torch.Tensor]:
        return [b.features for b in our_blocks(ours, our_input(f, shape, workspace=ws, origin=origin))]

    def ours_neck(f: SiteFrame) -> list[torch.Tensor]:
        return [ours.neck_rows(our_input(f, shape, workspace=ws, origin=origin)).features]

    def spconv_blocks(f: SiteFrame) -> list[torch.Tensor]:
        return [b.features for b in peer.blocks_forward(spconv_input(f, shape))]

    def spconv_neck(f: SiteFrame) -> list[torch.Tensor]:
        return [peer.neck_rows(spconv_input(f, shape))[1]]

    return {("ours", "blocks"): ours_blocks, ("spconv", "blocks"): spconv_blocks,
            ("ours", "backbone_neck"): ours_neck, ("spconv", "backbone_neck"): spconv_neck}


@torch.no_grad()
def time_threads(calls: dict, frames: list[SiteFrame], trials: int) -> dict:
    """At the current thread count: mean ms per frame per (engine, part), per-trial means, and determinism (every
    timed call against the warm-up call of the same frame)."""
    keys = list(calls)
    first = {}
    for i, f in enumerate(frames):  # warm-up, whose outputs are the determinism reference
        for k in keys:
            first[(k, i)] = [t.clone() for t in calls[k](f)]
    ms = np.zeros((len(keys), trials, len(frames)))
    equal = {k: True for k in keys}
    worst = dict.fromkeys(keys, 0.0)
    for t in range(trials):
        for i, f in enumerate(frames):
            order = keys if (t + i) % 2 == 0 else keys[::-1]
            for k in order:
                t0 = time.perf_counter()
                out = calls[k](f)
                ms[keys.index(k), t, i] = (time.perf_counter() - t0) * 1e3
                same, diff = same_outputs(first[(k, i)], out)
                equal[k] &= same
                worst[k] = max(worst[k], diff)
    rows = {}
    for j, (engine, part) in enumerate(keys):
        rows.setdefault(part, {})[engine] = {
            "mean_ms": float(ms[j].mean()), "median_ms": float(np.median(ms[j])),
            "trial_means_ms": [float(v) for v in ms[j].mean(axis=1)],
            "deterministic": equal[(engine, part)], "max_run_to_run_diff": worst[(engine, part)]}
    for r in rows.values():
        trial_ratio = np.asarray(r["spconv"]["trial_means_ms"]) / np.asarray(r["ours"]["trial_means_ms"])
        r["spconv_over_ours"] = r["spconv"]["mean_ms"] / r["ours"]["mean_ms"]
        r["spconv_over_ours_trials"] = [float(trial_ratio.min()), float(trial_ratio.max())]
    return rows


def _fmt_diffs(d: dict) -> str:
    return ", ".join(f"block {i + 1} {v:.1e}" for i, v in enumerate(d["blocks"])) + f", neck rows {d['neck']:.1e}"


def format_result(result: dict) -> str:
    """Markdown: the header (what ran, where), the time table per thread count, exactness and determinism."""
    h = result["header"]
    d = h["density"]
    lines = [f"# spconv {h['spconv']} (CPU build) vs ours (detector.sparse), {h['frames_source']}, grid "
             f"{h['grid'][0]} x {h['grid'][1]}, weights {h['weights']}",
             f"# runtime eager PyTorch {h['machine']['torch']} (ours: inference workspace; spconv: its modules, "
             f"ConvAlgo.Native); precision float32 timed, float64 exactness; threads {h['threads']}; allocator "
             f"{h['machine']['allocator']}; {h['machine']['cpu']}; load average (1 min) {h['machine']['loadavg_1m']}",
             f"# density D (active pillars / canvas cells): median {d['median']:.5f}, min {d['min']:.5f}, max "
             f"{d['max']:.5f} over {d['frames']} frames; {h['trials']} trials, interleaved per frame",
             "", "| threads | part | ours ms | spconv ms | spconv / ours (trials min-max) | ours bit-identical run to "
             "run | spconv bit-identical run to run (max diff) |", "|---|---|---|---|---|---|---|"]
    for threads, rows in result["timings"].items():
        for part, r in rows.items():
            o, s = r["ours"], r["spconv"]
            lo, hi = r["spconv_over_ours_trials"]
            lines.append(f"| {threads} | {part} | {o['mean_ms']:.2f} | {s['mean_ms']:.2f} | "
                         f"{r['spconv_over_ours']:.2f}x ({lo:.2f}-{hi:.2f}) | "
                         f"{'yes' if o['deterministic'] else 'NO'} ({o['max_run_to_run_diff']:.1e}) | "
                         f"{'yes' if s['deterministic'] else 'NO'} ({s['max_run_to_run_diff']:.1e}) |")
    lines.append("")
    for threads, frames in result["exactness"].items():
        for name, e in frames.items():
            lines.append(f"exactness, {threads} thread(s), frame {name} ({e['sites']} sites per block), max |diff|:")
            lines.append(f"  float64 ours vs dense conv: {_fmt_diffs(e['float64']['ours_vs_dense'])}")
            lines.append(f"  float64 spconv vs ours:     {_fmt_diffs(e['float64']['spconv_vs_ours'])}")
            lines.append(f"  float32 ours vs dense64:    {_fmt_diffs(e['float32']['ours_vs_dense64'])}")
            lines.append(f"  float32 spconv vs dense64:  {_fmt_diffs(e['float32']['spconv_vs_dense64'])}")
    for w in h["warnings"]:
        lines.append(f"warning: {w}")
    return "\n".join(lines)


def parse_threads(text: str) -> list[int]:
    """``"1,2"`` → ``[1, 2]``; an :class:`InputError` for anything but positive integers."""
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        values = []
    if not values or min(values) < 1:
        raise InputError(f"--threads must be a comma-separated list of positive integers, got {text!r}")
    return values


def main(argv: list[str] | None = None) -> int:
    """Run the comparison; 2 with one ``error:`` line on bad input or a missing spconv."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default="configs/models/mpchair_sparse.yaml", help="sparse experiment YAML")
    p.add_argument("--checkpoint", default=None, help="its weights (default: seeded random weights)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--data", type=Path, help="KITTI-format dataset folder")
    src.add_argument("--density", type=float, help="synthetic clustered sites at this density instead")
    p.add_argument("--split", default="test")
    p.add_argument("--frames", type=int, default=10)
    p.add_argument("--trials", type=int, default=3)
    p.add_argument("--threads", default="1,2", help="thread counts, comma-separated (default 1,2)")
    p.add_argument("--exact-frames", type=int, default=1, help="frames whose exactness is measured (float64 dense)")
    p.add_argument("--seed", type=int, default=0, help="random weights' and synthetic sites' seed")
    p.add_argument("--json-out", dest="json", type=Path, default=None,
                   help="also write the result as JSON to this file")
    args = p.parse_args(argv)
    return run_script(lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    try:
        threads = parse_threads(args.threads)
        if args.frames < 1 or args.trials < 1 or args.exact_frames < 0:
            raise InputError("--frames and --trials must be >= 1, --exact-frames >= 0")
        if args.density is not None and not 0 < args.density <= 1:
            raise InputError(f"--density must be in (0, 1], got {args.density}")
        if args.json is not None:
            check_writable(args.json)
        import_spconv()
        cfg = load_experiment(args.config)
        if cfg.model.backbone != "sparse":
            raise InputError(f"needs a sparse model, the config has backbone {cfg.model.backbone!r}", args.config)
        device = use_device("cpu", threads[0])
        net = load_model(cfg, args.checkpoint, device, seed=args.seed)
        ours = net.backbone
        if args.checkpoint is None:
            randomise_batchnorm_(ours, args.seed)
        peer = SpconvBackboneNeck(ours)
        shape = (int(cfg.model.output_shape[0]), int(cfg.model.output_shape[1]))
        if args.data is not None:
            frames = dataset_frames(net, cfg, str(args.data), args.split, args.frames)
            source = f"{args.frames} frame(s) of {args.data} {args.split}"
        else:
            frames = synthetic_frames(shape, args.density, args.frames, cfg.model.pfn_channels, args.seed)
            source = f"{args.frames} synthetic clustered frame(s) at D {args.density}"
        calls = _calls(ours, peer, shape, Workspace(), net)
        timings, exact, warnings = {}, {}, []
        for t in threads:
            use_device("cpu", t)
            w = oversubscription_warning(t, usable_cores(), load_1m())
            if w:
                warnings.append(w)
            exact[str(t)] = {f.name: exactness(ours, f, shape) for f in frames[: args.exact_frames]}
            timings[str(t)] = time_threads(calls, frames, args.trials)
    except (InputError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    cells = shape[0] * shape[1]
    result = {
        "header": {"spconv": spconv_version(), "config": str(args.config), "weights": args.checkpoint or
                   f"random (seed {args.seed}, BatchNorm statistics seeded)", "frames_source": source,
                   "grid": list(shape), "density": density_summary([f.coords.shape[0] / cells for f in frames]),
                   "threads": threads, "trials": args.trials, "precision": "float32",
                   "runtime": "eager PyTorch; ours with its inference workspace; spconv ConvAlgo.Native",
                   "machine": machine_info(device), "warnings": warnings},
        "timings": timings,
        "exactness": exact,
    }
    if args.json is not None:
        write_text(args.json, json.dumps(result, indent=2) + "\n")
    print(format_result(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
