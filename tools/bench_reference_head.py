"""The dense / sparse total-time ratio with the reference's head layout (three NCHW 1x1 convs) beside ours (one fused
GEMM): ``detector.bench.reference_head``. Interleaved per frame, one process; ms per frame.

    .venv/bin/python tools/bench_reference_head.py --config detector/configs/mpchair_dense.yaml \\
        --config detector/configs/mpchair_sparse.yaml --data DATASET --split test --frames 20 --trials 3 \\
        --json-out out.json

``--checkpoint`` once per ``--config`` (``-`` = random weights, the default for all); the table goes to stdout.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from detector.bench.reference_head import format_reference_head, run_reference_head_bench
from detector.bench.run import BenchModel, bench_checkpoints
from mpchair.core.atomic import check_writable, write_text
from mpchair.core.clitools import run_script
from mpchair.core.errors import InputError


def main(argv: list[str] | None = None) -> int:
    """Run the bench; 2 with one ``error:`` line on bad input."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", action="append", required=True, help="experiment YAML (repeat; the first is the "
                   "ratios' numerator)")
    p.add_argument("--checkpoint", action="append", default=[], help="weights per --config ('-': random)")
    p.add_argument("--data", type=Path, required=True, help="KITTI-format dataset folder")
    p.add_argument("--split", default="test")
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--trials", type=int, default=3)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=0, help="seed of random weights")
    p.add_argument("--json-out", type=Path, default=None, help="also write the result here")
    args = p.parse_args(argv)
    # a warning raised on the way (a checkpoint of another grid): one line each, after the result
    return run_script(lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    """The tool's work once its options are parsed; 2 with one ``error:`` line on bad input."""
    try:
        ckpts = bench_checkpoints(args.config, args.checkpoint)
        if args.json_out is not None:
            check_writable(args.json_out)
        result = run_reference_head_bench([BenchModel("", c, k) for c, k in zip(args.config, ckpts)], args.data,
                                          split=args.split, frames=args.frames, trials=args.trials,
                                          warmup=args.warmup, threads=args.threads, seed=args.seed)
    except (InputError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.json_out is not None:
        write_text(args.json_out, json.dumps(result, indent=2) + "\n")
    print(format_reference_head(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
