"""Dense vs sparse timings from one run: one SubM conv, the full backbone + neck, the whole detector end to end, a
training step and each sparse conv kind's forms (``detector.bench.sparse_ratios``, ``detector.bench.conv_forms``); a
closing summary prints the four targeted ratios.

    PYTHONPATH=. .venv/bin/python tools/bench_sparse.py [--threads 2] [--repeats 5] [--json-out out.json]
        [--skip subm backbone e2e train forms] [--data DATASET [--frames 8]] [--reuse-allocator] [--omp-passive]

The allocator can dominate CPU timings (reference note, timing note): glibc returns big freed buffers to the OS, so
every dense forward pays page faults. Run once as is and once with ``--reuse-allocator``. On a machine whose cores
are busy with other jobs, OpenMP's default spin-waiting can wreck the 2-thread sparse rows; ``--omp-passive`` sets
``OMP_WAIT_POLICY=PASSIVE`` (docs/sparse.md, "Busy machines"). Both are read only at process start, so the script
re-executes itself under them; the header prints the settings in force and every row its page faults per run.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from detector.bench.sparse_ratios import SECTIONS, RatioOptions, run_sparse_ratios
from detector.device import MALLOC_REUSE, OMP_PASSIVE, rerun_under
from mpchair.core.atomic import check_writable, write_text
from mpchair.core.clitools import run_script


def main(argv: list[str] | None = None) -> int:
    """Parse the options, re-run under the chosen environment, time; 2 with one ``error:`` line on bad input."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--train-repeats", type=int, default=3)
    p.add_argument("--skip", nargs="*", default=[], choices=SECTIONS)
    p.add_argument("--data", type=Path, default=None,
                   help="KITTI-format dataset: also time the forms on its first --frames test frames")
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--json-out", type=Path, default=None, help="also write the results as JSON to this path")
    p.add_argument("--reuse-allocator", action="store_true", help=f"re-run under {MALLOC_REUSE}")
    p.add_argument("--omp-passive", action="store_true", help=f"re-run under {OMP_PASSIVE} (busy machines)")
    args = p.parse_args(argv)
    rerun_under({**(MALLOC_REUSE if args.reuse_allocator else {}), **(OMP_PASSIVE if args.omp_passive else {})},
                [__file__, *(sys.argv[1:] if argv is None else argv)])
    opts = RatioOptions(threads=args.threads, repeats=args.repeats, train_repeats=args.train_repeats,
                        skip=frozenset(args.skip), data=args.data, frames=args.frames)
    return run_script(lambda: _run(opts, args.json_out))


def _run(opts: RatioOptions, json_out: Path | None) -> None:
    if json_out is not None:
        check_writable(json_out)
    results = run_sparse_ratios(opts)
    if json_out is not None:
        write_text(json_out, json.dumps(results, indent=1))


if __name__ == "__main__":
    sys.exit(main())
