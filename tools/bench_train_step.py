"""Time training steps of ``detector train`` at fp32 and at bf16 (``train.precision``), side by side, in one run.

Each measurement is a real ``detector.train.train`` call (the training loop itself, ``--max-steps`` steps on the first
frames of ``--split``, a fresh run folder) and reads the per-step seconds the loop logs in ``metrics.jsonl`` (forward,
target assignment, loss, backward, clipping and AdamW step; data loading excluded). The first ``--warmup`` steps are
dropped. fp32 and bf16 alternate for ``--rounds`` rounds on identical batches, so drift of a noisy machine hits both.
The GT-sampling database is built once and shared by every run.

    python tools/bench_train_step.py --data out/reproduce-full-e12-bf16/dataset \\
        --config configs/models/mpchair_dense_cpu.yaml --config configs/models/mpchair_sparse_cpu.yaml \\
        [--steps 30] [--warmup 5] [--rounds 2] [--threads 2] [--json OUT]

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

import torch

from detector.config import Precision
from detector.train import train

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
    p.add_argument("--json", type=Path, default=None, help="also write the results as JSON")
    args = p.parse_args(argv)
    if args.steps < 1 or args.warmup < 0 or args.rounds < 1:
        print("error: --steps and --rounds must be >= 1, --warmup >= 0", file=sys.stderr)
        return 2

    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_train_step_") as tmp:
        for config in args.config:
            times: dict[str, list[float]] = {pr: [] for pr in PRECISIONS}
            database = None
            for rnd in range(args.rounds):
                for pr in PRECISIONS:
                    run = Path(tmp) / f"{Path(config).stem}-{pr}-{rnd}"
                    run.mkdir()
                    if database is not None:
                        shutil.copyfile(database, run / "gt_database.npz")
                    train(config, args.data, run, max_steps=args.warmup + args.steps, threads=args.threads,
                          split=args.split, precision=pr, progress=False)
                    database = database or run / "gt_database.npz"
                    times[pr] += step_seconds(run, args.warmup)
            ms = {pr: 1000 * statistics.mean(t) for pr, t in times.items()}
            sd = {pr: 1000 * statistics.stdev(t) if len(t) > 1 else 0.0 for pr, t in times.items()}
            rows.append({"config": config, "steps": {pr: len(t) for pr, t in times.items()},
                         "mean_ms": ms, "std_ms": sd, "fp32_over_bf16": ms["fp32"] / ms["bf16"]})

    machine = {"cpu": platform.processor() or platform.machine(), "threads": args.threads, "torch": torch.__version__,
               "cpu_capability": torch.backends.cpu.get_cpu_capability(), "cores": os.cpu_count()}
    print(f"training step time (threads {args.threads}, torch {torch.__version__}, "
          f"{machine['cpu_capability']}; {args.rounds} rounds x {args.steps} steps after {args.warmup} warm-up)")
    print("| config | fp32 ms/step | bf16 ms/step | fp32 / bf16 |")
    print("|---|---|---|---|")
    for r in rows:
        print(f"| {Path(r['config']).name} | {r['mean_ms']['fp32']:.0f} ± {r['std_ms']['fp32']:.0f} | "
              f"{r['mean_ms']['bf16']:.0f} ± {r['std_ms']['bf16']:.0f} | {r['fp32_over_bf16']:.2f}x |")
    if args.json is not None:
        args.json.write_text(json.dumps({"models": rows, "machine": machine}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
