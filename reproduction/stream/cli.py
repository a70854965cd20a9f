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
    gaps      (in this process)       per setting, the sparse - dense sAP gap on the headline stream with its 95 %
                                      interval over episodes (whole episodes resampled: reproduction.stream.gaps)
    report    docs/streaming.md       the results section between its markers: the tables, the outcome per grid, what
                                      sAP cannot see, the gaps, the highest rate each model keeps up with, the curves
                                      (PNG), the speed at which sparse overtakes dense
    record    docs/results-data/stream  the report's inputs (every summary and latency log, the gaps, the streams'
                                      stream.json, commands.log, the held-out check) and the machine record
                                      (reproduction.stream.record): the report can be written again from it alone

A step whose outputs exist is skipped (``--force`` redoes it). ``--scale full`` (the default) replaces the results
section of ``docs/streaming.md`` and the record ``docs/results-data/stream``; ``--scale small`` is a few-minute
end-to-end check that writes ``<work folder>/streaming.md`` and ``<work folder>/record`` instead.
``--from-record docs/results-data/stream --steps report`` writes the results section from the record alone (where
there is no record yet, a block that says so and quotes no result). The trained models default to ``make reproduce``'s
(``out/reproduce-full/runs/{dense,sparse}/last.pt``), and its dataset (``--dataset``) is what the streamed houses are
checked against.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tempfile
import time
from pathlib import Path

from mpchair.core.clitools import run_script
from mpchair.core.errors import InputError
from reproduction.checkout import ROOT, require_checkout
from reproduction.runner import REUSE_ENV, Runner
from reproduction.steps import CONFIGS
from reproduction.stream.gaps import gap_path, read_gap, stream_gap, write_gap
from reproduction.stream.record import (
    MAX_FILE_BYTES,
    RECORD_JSON,
    RecordPlan,
    check_record_dest,
    machine_record,
    read_stream_record,
    restore_stream_record,
    save_stream_record,
)
from reproduction.stream.report import (
    houses_text,
    logged_text,
    no_record_section,
    plot_curves,
    results_section,
    write_section,
)
from reproduction.stream.results import house_check, read_runs, stream_frames
from reproduction.stream.steps import COMMAND_STEPS, STEPS, StreamPlan
from reproduction.stream.sweep import (
    GRIDS,
    HEADLINE,
    MODELS,
    SCALES,
    THREADS,
    Scale,
    eval_dir,
    settings,
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
    p.add_argument("--from-record", type=Path, default=None, metavar="DIR",
                   help="write the report from a streaming record alone (the record step's folder, e.g. "
                        "docs/results-data/stream; with --steps report); where DIR holds none yet, the block that "
                        "says so")
    p.add_argument("--record", type=Path, default=None, metavar="DIR",
                   help="where the record step writes (default: docs/results-data/stream for --scale full, "
                        "<work folder>/record otherwise)")
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


def _record_plan(args: argparse.Namespace, plan: StreamPlan) -> RecordPlan:
    """What the report and the record need of this invocation besides the work folder's files."""
    return RecordPlan(scale=args.scale, sizes=plan.scale, grids=tuple(args.grids.split(",")),
                      threads=tuple(int(t) for t in args.threads.split(",")), speeds=tuple(_floats(args.speeds)),
                      rates=tuple(_floats(args.rates)), heldout_seed=plan.heldout_seed,
                      checkpoints={m: _relative(c) for m, c in plan.checkpoints.items()}, notes=tuple(args.note))


def _report(rec: RecordPlan, out: Path, doc: Path, dataset: Path, record: tuple[str, dict] | None = None) -> Path:
    """Write the results section of ``doc`` from work folder ``out`` (a run's, or a record restored into it) and its
    curves beside ``doc``; ``record``: the record's folder (as the docs name it) and machine record, named in the
    opening note. ``doc``."""
    speeds, rates = list(rec.speeds), list(rec.rates)
    sets = settings(list(rec.grids), list(rec.threads))
    points = sweep_points(speeds, rates)
    runs = read_runs(out, points, sets)
    img_dir = doc.parent / "img" / ("streaming" if rec.scale == "full" else "streaming-" + rec.scale)
    figures = plot_curves(runs, sets[0], speeds, rates, img_dir)
    rel = {k: os.path.relpath(v, doc.parent) for k, v in figures.items()}
    frames = stream_frames(out, points)
    check = house_check(out, dataset)
    gaps = {s.name: g for s in sets if (g := read_gap(gap_path(out, s))) is not None}
    sc = rec.sizes
    made = ""
    if record is not None:
        name, machine = record
        made = (f" Record: `{name}` (its machine.json: {machine.get('cpu')}, widest vector ISA "
                f"{machine.get('widest_vector_isa')}, torch {machine.get('torch')}, written {machine.get('date_utc')} "
                "UTC).")
    note = (f"Written by `tools/reproduce_stream.py --scale {rec.scale}` ({len(check.streamed) if check else 0} "
            f"house(s) x {sc.episodes} episode(s), episodes cut at {sc.duration:g} s; frames per stream: "
            + ", ".join(f"{k} {n}" for k, n in frames.items()) + f"; {logged_text(out / 'commands.log')}; "
            "latencies are this machine's under its load at the time, see the machine line). "
            f"Models: {rec.checkpoints.get('dense')} and {rec.checkpoints.get('sparse')}, loaded into each grid's "
            "model (conv weights do not depend on the grid)." + made
            + "".join(" " + n.strip() for n in rec.notes) + "\n\n" + houses_text(check, rec.heldout_seed))
    write_section(doc, results_section(runs, sets, speeds, rates, rel, note, gaps))
    return doc


def _relative(path: Path) -> str:
    """``path`` relative to the checkout when it lies in it (the report reads the same on every machine)."""
    path = path.resolve()
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def run_gaps(plan: StreamPlan) -> None:
    """The ``gaps`` step: per setting whose two models were scored on the headline stream, the sparse - dense sAP gap
    with its 95 % interval over episodes (:mod:`reproduction.stream.gaps`; in this process, from the saved outputs
    and latency logs)."""
    for s in plan.settings:
        target = gap_path(plan.out, s)
        if not plan.todo("gaps", target):
            continue
        if plan.dry_run:
            print(f"[gaps] {s.name}: episode bootstrap of the sparse - dense sAP gap -> {target}")
            continue
        need = [eval_dir(plan.out, *HEADLINE, s, m) / f for m in MODELS for f in ("latency.json", "outputs")]
        if not all(p.exists() for p in need):
            print(f"[gaps] {s.name}: not measured, skipped")
            continue
        t0 = time.perf_counter()
        write_gap(plan.out, s, stream_gap(plan.out, s, resamples=plan.scale.gap_resamples))
        print(f"[gaps] {s.name}: wrote {target} ({time.perf_counter() - t0:.0f} s)")


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


def _from_record(args: argparse.Namespace, steps: list[str]) -> int:
    """``--from-record DIR --steps report``: the results block written from the record alone, restored into a
    temporary work folder (or ``--out``); where ``DIR`` holds no record yet, the block that says so."""
    if set(steps) != {"report"}:
        raise InputError("--from-record writes the report from a record: give --steps report")
    record = args.from_record
    name = _relative(record)
    if not (record / RECORD_JSON).exists():
        doc = args.docs or ROOT / "docs" / "streaming.md"
        write_section(doc, no_record_section(name))
        print(f"no streaming record at {record}: wrote the block that says so into {doc}")
        return 0
    rec, _, machine = read_stream_record(record)
    with tempfile.TemporaryDirectory(prefix="reproduce-stream-record-") as tmp:
        out = (args.out or Path(tmp)).resolve()
        restored = restore_stream_record(record, out)
        print(f"restored {len(restored)} file(s) of the record {record} into {out}")
        doc = args.docs or (ROOT / "docs" / "streaming.md" if rec.scale == "full" else out / "streaming.md")
        # the house check is the record's (house_check.json): no training dataset is read
        print(f"wrote {_report(rec, out, doc, out / 'no-dataset', (name, machine))}")
    return 0


def _main(argv: list[str] | None) -> int:
    args = _parser().parse_args(argv)
    require_checkout()  # it writes the clone's docs/: refused, in one line, anywhere else
    steps = [s.strip() for s in args.steps.split(",") if s.strip()]
    if [s for s in steps if s not in STEPS]:
        raise InputError(f"unknown step(s) in {args.steps!r}; choose from {list(STEPS)}")
    _check_args(args)
    if args.from_record is not None:
        return _from_record(args, steps)
    sc = SCALES[args.scale]
    overrides = {k: getattr(args, k) for k in ("heldout_houses", "episodes", "duration", "repeats", "sweep_repeats")
                 if getattr(args, k) is not None}
    sc = dataclasses.replace(sc, **overrides)
    out = (args.out or ROOT / "out" / f"reproduce-stream-{args.scale}").resolve()
    dest = args.record or (ROOT / "docs" / "results-data" / "stream" if args.scale == "full" else out / "record")
    if "record" in steps:  # before any step runs: a --record folder that is not this step's is never replaced
        check_record_dest(dest)
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
    run_gaps(plan)
    rec = _record_plan(args, plan)
    machine = machine_record() if "record" in steps and not args.dry_run else None
    if "report" in steps and not args.dry_run:
        doc = args.docs or (ROOT / "docs" / "streaming.md" if args.scale == "full" else plan.out / "streaming.md")
        # a report doc with one marker of the pair is an InputError naming it, and stays as it was
        print(f"wrote {_report(rec, out, doc, args.dataset, None if machine is None else (_relative(dest), machine))}")
    if "record" in steps and not args.dry_run:
        house_check(out, args.dataset)  # the held-out check goes into the record (a later report has no dataset)
        for rel in save_stream_record(out, dest, rec, machine):
            print(f"record: left out {rel} (over {MAX_FILE_BYTES >> 20} MB)")
        print(f"wrote the streaming record {dest}")
    print(f"total time {(time.perf_counter() - t0) / 60:.1f} min ({args.scale} scale, steps {','.join(steps)})")
    return 0
