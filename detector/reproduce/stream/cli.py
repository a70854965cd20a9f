"""``make reproduce-stream``: the paper's open question measured — streaming AP of dense vs sparse PointPillars on a
robot driving through the test houses, with latencies measured on this CPU (``docs/streaming.md``).

Steps (each a list of exact ``mpchair`` / ``detector`` command lines, run as subprocesses and recorded):

    streams   mpchair stream          one stream per (speed, rate): the speeds at 10 Hz, the rates at 0.5 m/s (the
                                      headline stream, 0.5 m/s at 10 Hz, is shared)
    measure   detector stream-eval    per model and stream: latency measured per processed frame (--latency-log),
                                      2 torch threads, and the outputs (--save-results): of every frame on the
                                      headline stream (for the offline AP), of the processed frames elsewhere
    score     detector stream-eval    ego and raw from the saved outputs, replaying the measured latencies exactly
                                      (--results, --latency LOG); and the oracle (a perfect detector) at each
                                      model's median latency on the headline stream: what the latency alone costs
    report    docs/streaming.md       the results section between its markers: the table, the curves (PNG), the
                                      speed at which sparse overtakes dense

A step whose outputs exist is skipped (``--force`` redoes it). ``--scale full`` (the default) replaces the results
section of ``docs/streaming.md``; ``--scale small`` is a few-minute end-to-end check that writes
``<work folder>/streaming.md`` instead. The trained models default to ``make reproduce``'s
(``out/reproduce-full/runs/{dense,sparse}/last.pt``), the houses to its synthetic houses.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

from detector.reproduce.runner import REUSE_ENV, ROOT, Runner
from detector.reproduce.steps import CONFIGS, house_ids
from detector.reproduce.stream.report import logged_text, plot_curves, results_section, write_section
from detector.reproduce.stream.results import read_runs, stream_frames
from detector.reproduce.stream.steps import COMMAND_STEPS, STEPS, StreamPlan
from detector.reproduce.stream.sweep import MODELS, SCALES, Scale, sweep_points


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scale", choices=sorted(SCALES), default="full")
    p.add_argument("--steps", default=",".join(STEPS), help=f"comma-separated subset of {','.join(STEPS)}")
    p.add_argument("--out", type=Path, default=None, help="work folder (default out/reproduce-stream-<scale>)")
    p.add_argument("--houses", type=Path, default=ROOT / "out" / "reproduce-full" / "houses",
                   help="houses root (default: make reproduce's synthetic houses)")
    p.add_argument("--house", action="append", default=None, help="house id (repeatable; default: every house)")
    for m in MODELS:
        p.add_argument(f"--{m}-config", type=Path, default=CONFIGS / f"mpchair_{m}_cpu.yaml")
        p.add_argument(f"--{m}-checkpoint", type=Path, default=ROOT / "out" / "reproduce-full" / "runs" / m / "last.pt")
    p.add_argument("--speeds", default="0.25,0.5,1.0", help="robot speeds of the speed sweep, m/s (at 10 Hz)")
    p.add_argument("--rates", default="5,10,20", help="sensor rates of the rate sweep, Hz (at 0.5 m/s)")
    p.add_argument("--episodes", type=int, default=None, help="episodes per house instead of the scale's")
    p.add_argument("--duration", type=float, default=None, help="episode cap, seconds, instead of the scale's")
    p.add_argument("--repeats", type=int, default=None,
                   help="measured latency: median of this many runs per processed frame instead of the scale's "
                        "(full: 2); 1 halves the measuring time")
    p.add_argument("--threads", type=int, default=2, help="torch threads of the measured detectors")
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
    """The invocation's plan: the scale's houses of the houses root (or ``--house``), the sweep, the models."""
    houses = args.house or house_ids(args.houses) or [f"<house ids from {args.houses}>"]
    houses = houses[: sc.houses] if sc.houses else houses
    return StreamPlan(out=out, scale=sc, steps=tuple(steps), houses_root=args.houses, houses=tuple(houses),
                      configs={m: getattr(args, f"{m}_config") for m in MODELS},
                      checkpoints={m: getattr(args, f"{m}_checkpoint") for m in MODELS},
                      points=tuple(sweep_points(_floats(args.speeds), _floats(args.rates))), threads=args.threads,
                      env=REUSE_ENV if args.allocator == "reuse" else {}, workers=args.workers, seed=args.seed,
                      force=args.force, dry_run=args.dry_run)


def _report(args: argparse.Namespace, plan: StreamPlan) -> Path:
    """Write the results section of the report (docs/streaming.md for the full scale) and its curves; its path."""
    speeds, rates = _floats(args.speeds), _floats(args.rates)
    runs = read_runs(plan.out, list(plan.points))
    doc = args.docs or (ROOT / "docs" / "streaming.md" if args.scale == "full" else plan.out / "streaming.md")
    img_dir = doc.parent / "img" / ("streaming" if args.scale == "full" else "streaming-" + args.scale)
    figures = plot_curves(runs, speeds, rates, img_dir)
    rel = {k: os.path.relpath(v, doc.parent) for k, v in figures.items()}
    frames = stream_frames(plan.out, list(plan.points))
    sc = plan.scale
    note = (f"Written by `tools/reproduce_stream.py --scale {args.scale}` ({len(plan.houses)} house(s) x "
            f"{sc.episodes} episode(s), episodes cut at {sc.duration:g} s; frames per stream: "
            + ", ".join(f"{k} {n}" for k, n in frames.items()) + f"; {logged_text(plan.out / 'commands.log')}; "
            "latencies are this machine's under its load at the time, see the machine line)."
            + "".join(" " + n.strip() for n in args.note))
    write_section(doc, results_section(runs, speeds, rates, rel, note))
    return doc


def main(argv: list[str] | None = None) -> int:
    """``tools/reproduce_stream.py``: run the steps asked for in the work folder and write the results section; 2 on
    a bad option or a missing checkpoint."""
    args = _parser().parse_args(argv)
    steps = [s.strip() for s in args.steps.split(",") if s.strip()]
    if [s for s in steps if s not in STEPS]:
        print(f"error: unknown step(s) in {args.steps!r}; choose from {list(STEPS)}", file=sys.stderr)
        return 2
    sc = SCALES[args.scale]
    sc = dataclasses.replace(sc, episodes=args.episodes or sc.episodes, duration=args.duration or sc.duration,
                             repeats=sc.repeats if args.repeats is None else args.repeats)
    if sc.repeats < 1:
        print("error: --repeats must be >= 1", file=sys.stderr)
        return 2
    out = (args.out or ROOT / "out" / f"reproduce-stream-{args.scale}").resolve()
    out.mkdir(parents=True, exist_ok=True)
    r = Runner(args.dry_run, out / "commands.log")
    plan = _plan(args, sc, steps, out)
    t0 = time.perf_counter()
    missing = [c for c in plan.checkpoints.values() if not c.exists()]
    if missing and not args.dry_run and ({"measure", "score"} & set(steps)):
        print(f"error: checkpoint(s) not found: {', '.join(map(str, missing))} (run make reproduce first, or pass "
              "--dense-checkpoint / --sparse-checkpoint)", file=sys.stderr)
        return 2
    for run_step in COMMAND_STEPS:
        run_step(plan, r)
    if "report" in steps and not args.dry_run:
        print(f"wrote {_report(args, plan)}")
    print(f"total time {(time.perf_counter() - t0) / 60:.1f} min ({args.scale} scale, steps {','.join(steps)})")
    return 0
