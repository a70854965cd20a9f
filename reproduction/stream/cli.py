"""``make reproduce-stream``: the paper's open question measured — streaming AP of dense vs sparse PointPillars on a
robot driving through houses the models were not trained on, with latencies measured on this CPU at the paper's
768 x 512 grid and the CPU-sized 288 x 144 one, under 2 and 1 torch threads (``docs/streaming.md``).

Steps (each a list of exact ``mpchair`` / ``detector`` command lines, run as subprocesses and recorded):

    houses    mpchair synth           held-out houses for the streams (a seed other than make reproduce's, checked
                                      against its training dataset in the report); --houses streams given ones
    streams   mpchair stream          one stream per (speed, rate): the speeds at 10 Hz, the rates at 0.5 m/s (the
                                      headline stream, 0.5 m/s at 10 Hz, is shared)
    measure   detector stream-eval    per model and setting (grid x threads): latency measured per processed frame
                                      (--latency-log) and the outputs (--save-results): on the headline stream
                                      every setting, with one offline pass per grid (the offline AP); on the other
                                      streams the headline setting (768 x 512, 2 threads)
    score     detector stream-eval    ego and raw from the saved outputs, replaying the measured latencies exactly
                                      (--results, --latency LOG); and the oracle (a perfect detector) at each
                                      measured median latency on the headline stream: what the latency alone costs
    report    docs/streaming.md       the results section between its markers: the tables, the highest rate each
                                      model keeps up with, the curves (PNG), the speed at which sparse overtakes dense

A step whose outputs exist is skipped (``--force`` redoes it). ``--scale full`` (the default) replaces the results
section of ``docs/streaming.md``; ``--scale small`` is a few-minute end-to-end check that writes
``<work folder>/streaming.md`` instead. The trained models default to ``make reproduce``'s
(``out/reproduce-full/runs/{dense,sparse}/last.pt``), and its dataset (``--dataset``) is what the streamed houses are
checked against.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path

from mpchair.core.clitools import run_script
from mpchair.core.errors import InputError
from reproduction.checkout import ROOT, require_checkout
from reproduction.runner import REUSE_ENV, Runner
from reproduction.steps import CONFIGS
from reproduction.stream.report import houses_text, logged_text, plot_curves, results_section, write_section
from reproduction.stream.results import check_houses, read_runs, stream_frames
from reproduction.stream.steps import COMMAND_STEPS, STEPS, StreamPlan
from reproduction.stream.sweep import (
    GRIDS,
    HEADLINE,
    MODELS,
    SCALES,
    THREADS,
    Scale,
    settings,
    stream_dir,
    sweep_points,
)

#: The seed of the held-out houses (make reproduce synthesizes its houses with its --seed, 0 by default).
HELDOUT_SEED = 1000


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scale", choices=sorted(SCALES), default="full")
    p.add_argument("--steps", default=",".join(STEPS), help=f"comma-separated subset of {','.join(STEPS)}")
    p.add_argument("--out", type=Path, default=None, help="work folder (default out/reproduce-stream-<scale>)")
    p.add_argument("--houses", type=Path, default=None,
                   help="stream these houses instead of synthesizing held-out ones (the report says whether the "
                        "models were trained on them)")
    p.add_argument("--house", action="append", default=None, help="house id of --houses (repeatable; default: all)")
    p.add_argument("--heldout-seed", type=int, default=HELDOUT_SEED,
                   help=f"mpchair synth seed of the held-out houses (default {HELDOUT_SEED}; make reproduce's "
                        "houses use its --seed, 0)")
    p.add_argument("--dataset", type=Path, default=ROOT / "out" / "reproduce-full" / "dataset",
                   help="the models' training dataset, to check that the streamed houses are not in it")
    for m in MODELS:
        p.add_argument(f"--{m}-checkpoint", type=Path, default=ROOT / "out" / "reproduce-full" / "runs" / m / "last.pt")
    p.add_argument("--grids", default=",".join(GRIDS),
                   help="pseudo-image grids to measure at (the first is the headline's and the sweep's)")
    p.add_argument("--threads", default=",".join(map(str, THREADS)),
                   help="torch thread budgets to measure under (the first is the sweep's)")
    p.add_argument("--speeds", default="0.25,0.5,1.0", help="robot speeds of the speed sweep, m/s (at 10 Hz)")
    p.add_argument("--rates", default="5,10,20", help="sensor rates of the rate sweep, Hz (at 0.5 m/s)")
    p.add_argument("--heldout-houses", type=int, default=None, help="held-out houses instead of the scale's")
    p.add_argument("--episodes", type=int, default=None, help="episodes per house instead of the scale's")
    p.add_argument("--duration", type=float, default=None, help="episode cap, seconds, instead of the scale's")
    p.add_argument("--repeats", type=int, default=None,
                   help="measured latency on the headline stream: median of this many runs per processed frame "
                        "instead of the scale's (full: 3)")
    p.add_argument("--sweep-repeats", type=int, default=None,
                   help="the same on the sweep's other streams (full: 1)")
    p.add_argument("--allocator", choices=["reuse", "default"], default="reuse",
                   help="glibc allocator setting while measuring (docs/benchmarks.md; reuse = what a deployment sets)")
    p.add_argument("--workers", type=int, default=2, help="mpchair stream worker processes")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--docs", type=Path, default=None,
                   help="report file (default: docs/streaming.md for --scale full, <work folder>/streaming.md else)")
    p.add_argument("--note", action="append", default=[],
                   help="a sentence for the report's opening line, e.g. how the run deviated (repeatable)")
    p.add_argument("--force", action="store_true", help="redo steps whose outputs exist")
    p.add_argument("--dry-run", action="store_true", help="print the commands only")
    return p


def _floats(text: str) -> list[float]:
    return sorted(float(x) for x in text.split(",") if x.strip())


def _plan(args: argparse.Namespace, sc: Scale, steps: list[str], out: Path) -> StreamPlan:
    """The invocation's plan: the held-out houses (or ``--houses``), the sweep, the settings, the models."""
    given = args.houses is not None
    return StreamPlan(out=out, scale=sc, steps=tuple(steps), houses_root=args.houses if given else out / "houses",
                      houses=tuple(args.house or ()), heldout_seed=None if given else args.heldout_seed,
                      configs=CONFIGS, checkpoints={m: getattr(args, f"{m}_checkpoint") for m in MODELS},
                      points=tuple(sweep_points(_floats(args.speeds), _floats(args.rates))),
                      settings=tuple(settings(args.grids.split(","), [int(t) for t in args.threads.split(",")])),
                      env=REUSE_ENV if args.allocator == "reuse" else {}, workers=args.workers, seed=args.seed,
                      force=args.force, dry_run=args.dry_run)


def _report(args: argparse.Namespace, plan: StreamPlan) -> Path:
    """Write the results section of the report (docs/streaming.md for the full scale) and its curves; its path."""
    speeds, rates = _floats(args.speeds), _floats(args.rates)
    runs = read_runs(plan.out, list(plan.points), list(plan.settings))
    doc = args.docs or (ROOT / "docs" / "streaming.md" if args.scale == "full" else plan.out / "streaming.md")
    img_dir = doc.parent / "img" / ("streaming" if args.scale == "full" else "streaming-" + args.scale)
    figures = plot_curves(runs, plan.settings[0], speeds, rates, img_dir)
    rel = {k: os.path.relpath(v, doc.parent) for k, v in figures.items()}
    frames = stream_frames(plan.out, list(plan.points))
    sc = plan.scale
    check = check_houses(stream_dir(plan.out, *HEADLINE), args.dataset)
    note = (f"Written by `tools/reproduce_stream.py --scale {args.scale}` ({len(check.streamed) if check else 0} "
            f"house(s) x {sc.episodes} episode(s), episodes cut at {sc.duration:g} s; frames per stream: "
            + ", ".join(f"{k} {n}" for k, n in frames.items()) + f"; {logged_text(plan.out / 'commands.log')}; "
            "latencies are this machine's under its load at the time, see the machine line). "
            f"Models: {_relative(plan.checkpoints['dense'])} and {_relative(plan.checkpoints['sparse'])}, loaded "
            "into each grid's model (conv weights do not depend on the grid)."
            + "".join(" " + n.strip() for n in args.note) + "\n\n" + houses_text(check, plan.heldout_seed))
    write_section(doc, results_section(runs, list(plan.settings), speeds, rates, rel, note))
    return doc


def _relative(path: Path) -> str:
    """``path`` relative to the checkout when it lies in it (the report reads the same on every machine)."""
    path = path.resolve()
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def _check_args(args: argparse.Namespace) -> None:
    """An :class:`InputError` for bad options."""
    try:
        threads = [int(t) for t in args.threads.split(",")]
        _floats(args.speeds), _floats(args.rates)
    except ValueError:
        raise InputError("--threads, --speeds and --rates take comma-separated numbers") from None
    grids = args.grids.split(",")
    if not grids or [g for g in grids if g not in GRIDS]:
        raise InputError(f"--grids takes a comma-separated subset of {','.join(GRIDS)}")
    if not threads or min(threads) < 1:
        raise InputError("--threads must be >= 1")
    for name in ("repeats", "sweep_repeats", "heldout_houses", "episodes"):
        if getattr(args, name) is not None and getattr(args, name) < 1:
            raise InputError(f"--{name.replace('_', '-')} must be >= 1")


def main(argv: list[str] | None = None) -> int:
    """``tools/reproduce_stream.py``: run the steps asked for in the work folder and write the results section; 2 on
    a bad option or a missing checkpoint (one ``error:`` line: the console scripts' error path)."""
    return run_script(lambda: _main(argv))


def _main(argv: list[str] | None) -> int:
    args = _parser().parse_args(argv)
    require_checkout()  # it writes the clone's docs/: refused, in one line, anywhere else
    steps = [s.strip() for s in args.steps.split(",") if s.strip()]
    if [s for s in steps if s not in STEPS]:
        raise InputError(f"unknown step(s) in {args.steps!r}; choose from {list(STEPS)}")
    _check_args(args)
    sc = SCALES[args.scale]
    overrides = {k: getattr(args, k) for k in ("heldout_houses", "episodes", "duration", "repeats", "sweep_repeats")
                 if getattr(args, k) is not None}
    sc = dataclasses.replace(sc, **overrides)
    out = (args.out or ROOT / "out" / f"reproduce-stream-{args.scale}").resolve()
    out.mkdir(parents=True, exist_ok=True)
    r = Runner(args.dry_run, out / "commands.log")
    plan = _plan(args, sc, steps, out)
    t0 = time.perf_counter()
    missing = [c for c in plan.checkpoints.values() if not c.exists()]
    if missing and not args.dry_run and ({"measure", "score"} & set(steps)):
        raise InputError(f"checkpoint(s) not found: {', '.join(map(str, missing))} (run make reproduce first, or pass "
                         "--dense-checkpoint / --sparse-checkpoint)")
    for run_step in COMMAND_STEPS:
        run_step(plan, r)
    if "report" in steps and not args.dry_run:
        # a report doc with one marker of the pair is an InputError naming it, and stays as it was
        print(f"wrote {_report(args, plan)}")
    print(f"total time {(time.perf_counter() - t0) / 60:.1f} min ({args.scale} scale, steps {','.join(steps)})")
    return 0
