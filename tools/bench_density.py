"""The dense / sparse backbone runtime ratio against pseudo-image density D, the op-count ratio beside it, and where
they cross (``detector.bench.density``): clustered synthetic sites from D = 0.002 to KITTI's 0.0246 on the paper's
768 x 512 canvas, random weights, the two models interleaved per frame in one process.

    .venv/bin/python tools/bench_density.py --threads 2 --json-out curve.json --plot curve.png \\
        [--data DATASET --split test --real-frames 5] [--mark "this dataset=0.0061"]

``--data``: also time that many real frames of the split at their own D (a check of the synthetic curve).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from detector.bench.density import DENSITIES, density_curve, format_curve, plot_curve
from detector.config import CONFIG_DIR
from mpchair.core.atomic import check_writable, write_text
from mpchair.core.clitools import run_script
from mpchair.core.errors import InputError


def _mark(text: str) -> tuple[str, float]:
    """``LABEL=D`` of ``--mark`` as (label, D); anything else is an :class:`InputError`."""
    label, _, value = text.rpartition("=")
    try:
        d = float(value)
    except ValueError:
        d = float("nan")
    if not label or not 0 < d < 1:
        raise InputError(f"--mark takes LABEL=D with 0 < D < 1, got {text!r}")
    return label, d


def main(argv: list[str] | None = None) -> int:
    """Measure the curve, print its table, write its JSON and plot; 2 with one ``error:`` line on bad input."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dense-config", type=Path, default=CONFIG_DIR / "mpchair_dense.yaml")
    p.add_argument("--sparse-config", type=Path, default=CONFIG_DIR / "mpchair_sparse.yaml")
    p.add_argument("--densities", default=",".join(f"{d:g}" for d in DENSITIES), help="comma-separated D values")
    p.add_argument("--frames", type=int, default=3, help="synthetic frames (seeds) per density")
    p.add_argument("--trials", type=int, default=3, help="timed passes over each density's frames")
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--data", type=Path, default=None, help="dataset whose real frames are timed at their own D too")
    p.add_argument("--split", default="test")
    p.add_argument("--real-frames", type=int, default=5)
    p.add_argument("--mark", action="append", default=[], help="LABEL=D: a vertical line on the plot (repeatable)")
    p.add_argument("--json-out", type=Path, default=None)
    p.add_argument("--plot", type=Path, default=None)
    args = p.parse_args(argv)
    # a warning raised on the way (a checkpoint of another grid): one line each, after the result
    return run_script(lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    """The tool's work once its options are parsed; 2 with one ``error:`` line on bad input."""
    try:
        densities = [float(x) for x in args.densities.split(",") if x.strip()]
        marks = dict(_mark(m) for m in args.mark)
        for out in (args.json_out, args.plot):
            if out is not None:
                check_writable(out)
        real = []
        if args.data is not None:
            from detector.config import load_experiment
            from detector.data.experiment import load_eval_frames

            frames = load_eval_frames(load_experiment(args.dense_config), args.data, args.split, args.real_frames)
            real = [(f.frame_id, f.points) for f in frames]
        result = density_curve(args.dense_config, args.sparse_config, densities=densities, frames=args.frames,
                               trials=args.trials, warmup=args.warmup, threads=args.threads, seed=args.seed,
                               real=real)
    except ValueError as e:
        print(f"error: --densities: {e}", file=sys.stderr)
        return 2
    except (InputError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.json_out is not None:
        write_text(args.json_out, json.dumps(result, indent=2) + "\n")
    if args.plot is not None:
        plot_curve(result, args.plot, marks)
    print(format_curve(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
