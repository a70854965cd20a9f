"""Time training steps of ``detector train`` at fp32 and at bf16 (``train.precision``), side by side, in one run, and
the step-time ratio of the first config to each other one (dense / sparse).

Each measurement is a real ``detector.train.train`` call (the training loop itself, ``--max-steps`` steps on the first
frames of ``--split``, a fresh run folder) and reads the per-step seconds the loop logs in ``metrics.jsonl`` (forward,
target assignment, loss, backward, clipping and AdamW step; data loading excluded). The first ``--warmup`` steps are
dropped. fp32 and bf16 alternate for ``--rounds`` rounds on identical batches, so drift of a noisy machine hits both.
The GT-sampling database is built once per config and shared by its runs.

    python tools/bench_train_step.py --data out/reproduce-full-e12-bf16/dataset \\
        --config detector/configs/mpchair_dense_cpu.yaml --config detector/configs/mpchair_sparse_cpu.yaml \\
        [--steps 30] [--warmup 5] [--rounds 2] [--threads 2] [--precision fp32 [--precision bf16]]
        [--gemm auto [--gemm mkl]] [--json-out OUT]

With several configs the rounds interleave them too (round 1: every config at every precision, then round 2, ...),
so load drift hits every config alike; the table's last rows are ``first / other`` step-time ratios per precision.
``--gemm auto --gemm mkl`` times every config under both fp32 GEMM settings (``detector.ops.gemm.gemm_backend``: oneDNN
or MKL) in the same interleaved rounds, with the ratios per setting.

Set ``MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=68719476736`` as for training (docs/training.md, "Speed on CPU").
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import sys
import tempfile
from pathlib import Path
from typing import get_args

# oneDNN keeps its JIT-compiled kernels in an LRU cache of 1,024 by default. One training run of the sparse model
# stays within it (a 60-step fp32 run after 20 warm-up steps: 76 ms per step at 1,024, 75 at 8,192), but the runs
# this tool interleaves in one process do not: bf16 runs evicted the fp32 runs' bucketed GEMM kernels, which then
# recompiled, and the sparse fp32 step measured 95 instead of 85 ms (dense unchanged). Read at oneDNN's first use,
# so set before torch is imported; an explicit setting wins.
os.environ.setdefault("ONEDNN_PRIMITIVE_CACHE_CAPACITY", "8192")

import torch  # noqa: E402

from detector.config import Precision
from detector.ops import gemm
from detector.train import train
from mpchair.core.errors import InputError

PRECISIONS = get_args(Precision)  # ("fp32", "bf16"): the ratio is fp32 / bf16


def step_seconds(run: Path, warmup: int) -> list[float]:
    """Per-step seconds logged by the training loop in ``run/metrics.jsonl``, without the first ``warmup`` steps."""
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    return [r["time_s"] for r in records if r["kind"] == "step" and r["step"] > warmup]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", action="append", required=True, help="experiment YAML (repeat for several)")
    p.add_argument("--data", required=True, type=Path, help="KITTI-format dataset")
    p.add_argument("--split", default="train")
    p.add_argument("--steps", type=int, default=30, help="timed steps per run (after the warm-up)")
    p.add_argument("--warmup", type=int, default=5, help="untimed steps at the start of every run")
    p.add_argument("--rounds", type=int, default=2, help="fp32 / bf16 alternations per config")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--precision", action="append", choices=PRECISIONS, default=None,
                   help="precisions to time (repeat; default: all)")
    p.add_argument("--gemm", action="append", choices=("auto", "mkl"), default=None,
                   help="fp32 GEMM library setting to time (repeat to time both side by side; default: "
                        "DETECTOR_GEMM, i.e. auto = oneDNN)")
    p.add_argument("--json-out", type=Path, default=None, help="also write the results as JSON")
    args = p.parse_args(argv)
    if args.steps < 1 or args.warmup < 0 or args.rounds < 1:
        print("error: --steps and --rounds must be >= 1, --warmup >= 0", file=sys.stderr)
        return 2

    precisions = tuple(args.precision) if args.precision else PRECISIONS
    try:  # the environment's choice, read once here (detector.ops.gemm reads no environment)
        libraries = tuple(dict.fromkeys(args.gemm)) if args.gemm else (
            gemm.parse_backend(os.environ.get("DETECTOR_GEMM", "auto")),)
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    variants = [(c, lib) for lib in libraries for c in args.config]
    times: dict[tuple[str, str], dict[str, list[float]]] = {v: {pr: [] for pr in precisions} for v in variants}
    with tempfile.TemporaryDirectory(prefix="bench_train_step_") as tmp:
        database: dict[str, Path] = {}  # built once per config, then shared by its runs
        for rnd in range(args.rounds):
            for config, lib in variants:
                for pr in precisions:
                    run = Path(tmp) / f"{Path(config).stem}-{lib}-{pr}-{rnd}"
                    run.mkdir()
                    if config in database:
                        shutil.copyfile(database[config], run / "gt_database.npz")
                    with gemm.gemm_backend(lib):  # read at every product, so one process times both
                        train(config, args.data, run, max_steps=args.warmup + args.steps, threads=args.threads,
                              split=args.split, precision=pr, progress=False)
                    database.setdefault(config, run / "gt_database.npz")
                    times[(config, lib)][pr] += step_seconds(run, args.warmup)
    rows = []
    for (config, lib), t in times.items():
        ms = {pr: 1000 * statistics.mean(v) for pr, v in t.items()}
        sd = {pr: 1000 * statistics.stdev(v) if len(v) > 1 else 0.0 for pr, v in t.items()}
        row = {"config": config, "gemm": lib, "steps": {pr: len(v) for pr, v in t.items()}, "mean_ms": ms,
               "std_ms": sd}
        if "fp32" in ms and "bf16" in ms:
            row["fp32_over_bf16"] = ms["fp32"] / ms["bf16"]
        rows.append(row)
    ratios = []
    for lib in libraries:  # first config / each other one, at the same GEMM setting
        same = [r for r in rows if r["gemm"] == lib]
        ratios += [{"first": same[0]["config"], "other": r["config"], "gemm": lib,
                    "ratio": {pr: same[0]["mean_ms"][pr] / r["mean_ms"][pr] for pr in precisions}} for r in same[1:]]

    machine = {"cpu": platform.processor() or platform.machine(), "threads": args.threads, "torch": torch.__version__,
               "cpu_capability": torch.backends.cpu.get_cpu_capability(), "cores": os.cpu_count(),
               "onednn_primitive_cache": int(os.environ["ONEDNN_PRIMITIVE_CACHE_CAPACITY"])}
    print(f"training step time (threads {args.threads}, torch {torch.__version__}, "
          f"{machine['cpu_capability']}; {args.rounds} rounds x {args.steps} steps after {args.warmup} warm-up; "
          f"DETECTOR_GEMM {' / '.join(libraries)}: fp32 products in {' / '.join(gemm.library(x) for x in libraries)}; "
          f"oneDNN kernel cache {machine['onednn_primitive_cache']})")
    print("| config | GEMM | " + " | ".join(f"{pr} ms/step" for pr in precisions) + " |"
          + (" fp32 / bf16 |" if len(precisions) == 2 else ""))
    print("|---|---|" + "---|" * (len(precisions) + (len(precisions) == 2)))
    for r in rows:
        cells = [f"{r['mean_ms'][pr]:.0f} ± {r['std_ms'][pr]:.0f}" for pr in precisions]
        if "fp32_over_bf16" in r:
            cells.append(f"{r['fp32_over_bf16']:.2f}x")
        print(f"| {Path(r['config']).name} | {r['gemm']} | " + " | ".join(cells) + " |")
    for q in ratios:
        cells = [f"{q['ratio'][pr]:.2f}x" for pr in precisions]
        print(f"| {Path(q['first']).stem} / {Path(q['other']).stem} | {q['gemm']} | " + " | ".join(cells)
              + (" |" if len(precisions) == 1 else " | |"))
    if args.json_out is not None:
        args.json_out.write_text(json.dumps({"models": rows, "ratios": ratios, "machine": machine}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
